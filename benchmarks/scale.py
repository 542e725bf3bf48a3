"""Memory and time of the default DE path against the length of the recordings (issue #15).

Four recordings of n samples each (the clean bus-15-fault training runs of generator 31 from
``jaxdmd.grid.benchmark_protocol``, simulated once and cached, with Gaussian noise of 1 % of each
state's range added), then, each stage timed in a fresh subprocess per size:

  derivatives      ``Dataset.with_estimated_derivatives()`` of the four recordings (default
                   estimator, split at the events);
  matched_filter   ``jaxdmd.data.matched_filter`` of one recording's grid and events;
  estimator_gains  ``jaxdmd.problems.estimator_gains`` of one recording (the noise weights);
  de_problem       ``jaxdmd.problems.de_problem(matched=True, weighted=True)`` of the four (the
                   default DE problem; its matched operator and noise weights are computed once
                   per distinct grid and events, here once: the four share them);
  fit_seed         ``jaxdmd.search.init``: the linear seed skeleton fitted on that problem (the
                   first search round without a model), with the default discovery's DE search
                   settings (``DiscoveryConfig().de_search()``);
  search_round     one round of that search as the default discovery runs it: the offline
                   proposer built on the problem (``OfflineFactory``), ``search.prompts``, its
                   answers, ``search.step`` (every candidate fitted);

and with ``--model DIR`` (a finished run's folder, e.g. the default run's ``runs/demo``: its
state and algebraic equations) two stages of what follows the searches:

  model_states     ``jaxdmd.refine.model_states``: the states estimated by the Kalman smoother
                   with the state equations as process model (the AE loop's regressors);
  joint_refit      ``jaxdmd.refine.refit_joint`` with 3 BFGS steps: the likelihood of all
                   recordings and its gradient, the most memory-hungry stage of the default
                   discovery after the searches.

Two ways to make n samples from the 10 s runs (``--mode``):

  long  the 0.01 s step kept, the run repeated end to end (with its fault events) until n
        samples: 1e5 samples are 1000 s. The estimator's band width stays 31 samples, so every
        stage should be linear in n;
  fine  10 s kept, the run interpolated (linearly) to n samples: the band width grows like n
        (the windows are fixed in seconds), so the band stages grow like n^2 however built.

Per stage: wall time, the peak of NumPy/Python allocations (tracemalloc, which also slows
Python-heavy code a little) and the process's peak RSS after the stage (ru_maxrss: JAX's
buffers included, monotone). Writes ``scale.json`` and ``scale.md`` (a table) to ``--out``.

    python benchmarks/scale.py --sizes 1000 10000 100000 [--mode long|fine] [--out DIR]
                               [--model runs/demo]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import time
import tracemalloc
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

STAGES = (
    "derivatives",
    "matched_filter",
    "estimator_gains",
    "de_problem",
    "fit_seed",
    "search_round",
)
POST_STAGES = ("model_states", "joint_refit")  # with --model


def source(cache: Path) -> Path:
    """Simulate the four clean training runs once (cached as .npz)."""
    if cache.exists():
        return cache
    import jaxdmd  # noqa: F401
    from jaxdmd.grid import benchmark_protocol

    data = benchmark_protocol(generators=(31,), operating_points=4, noise=0.0)
    runs = data.train_clean[31]
    first = runs[0]
    np.savez(
        cache,
        t=np.asarray(first.t),
        values=np.stack([np.asarray(ds.values) for ds in runs]),
        meta=np.array(
            json.dumps(
                {
                    "names": list(first.names),
                    "roles": list(first.roles),
                    "events": [list(ds.events) for ds in runs],
                }
            )
        ),
    )
    return cache


def recordings(cache: Path, n: int, mode: str, seed: int = 0) -> list:
    """Four noisy recordings of n samples from the cached runs (derivatives not yet estimated:
    zeros, replaced in the 'derivatives' stage)."""
    from jaxdmd.data import Dataset

    with np.load(cache) as z:
        t0, values, meta = z["t"], z["values"], json.loads(str(z["meta"]))
    names, roles = meta["names"], dict(zip(meta["names"], meta["roles"], strict=True))
    states = [nm for nm in names if roles[nm] == "state"]
    rng = np.random.default_rng(seed)
    out = []
    for r in range(values.shape[0]):
        v0, ev0 = values[r], meta["events"][r]
        if mode == "long":
            dt = float(np.median(np.diff(t0)))
            period = t0[-1] - t0[0] + dt
            copies = -(-n // len(t0))
            t = np.concatenate([t0 + k * period for k in range(copies)])[:n]
            v = np.concatenate([v0] * copies)[:n]
            events = tuple(
                e + k * period for k in range(copies) for e in ev0 if e + k * period < t[-1]
            )
        else:
            t = np.linspace(t0[0], t0[-1], n)
            v = np.stack([np.interp(t, t0, v0[:, j]) for j in range(v0.shape[1])], axis=1)
            events = tuple(ev0)
        v = v.copy()
        for nm in states:
            j = names.index(nm)
            v[:, j] += 0.01 * np.ptp(v[:, j]) * rng.standard_normal(n)
        out.append(
            Dataset.create(
                t,
                [(nm, v[:, j]) for j, nm in enumerate(names)],
                roles,
                derivatives={s: np.zeros(n) for s in states},
                events=events,
                label=f"run {r}",
            )
        )
    return out


def child(cache: Path, n: int, mode: str, model_dir: Path | None = None) -> dict:
    """Run the stages on recordings of n samples in this process; one dict of figures."""
    import jax

    import jaxdmd
    from jaxdmd import search
    from jaxdmd.data import matched_filter
    from jaxdmd.pipeline import DiscoveryConfig, OfflineFactory
    from jaxdmd.problems import de_problem, estimator_gains

    datasets = recordings(cache, n, mode)
    figures: dict[str, dict] = {}
    tracemalloc.start()

    def stage(name, fn):
        tracemalloc.reset_peak()
        t_start = time.perf_counter()
        out = fn()
        seconds = time.perf_counter() - t_start
        figures[name] = {
            "seconds": round(seconds, 3),
            "tracemalloc_peak_mb": round(tracemalloc.get_traced_memory()[1] / 2**20, 1),
            "maxrss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
        }
        return out

    datasets = stage("derivatives", lambda: [ds.with_estimated_derivatives() for ds in datasets])
    index, _ = stage(
        "matched_filter", lambda: matched_filter(datasets[0].t, events=datasets[0].events)
    )
    stage("estimator_gains", lambda: estimator_gains(datasets[0]))
    problem, contract = stage(
        "de_problem", lambda: de_problem(datasets, matched=True, weighted=True)
    )
    config = DiscoveryConfig().de_search()
    state = stage("fit_seed", lambda: search.init(problem, contract, jax.random.key(0), config))
    scores = [e.score for island in state.archive.islands for e in island.entries]

    def one_round():
        proposer = OfflineFactory()(problem, "DE")
        after, requests = search.prompts(state)
        return search.step(after, proposer.propose(requests))

    _, report = stage("search_round", one_round)
    if model_dir is not None:
        from jaxdmd.refine import model_states, refit_joint

        model = jaxdmd.load(model_dir)
        estimates = stage("model_states", lambda: model_states(model.de, datasets))
        stage(
            "joint_refit",
            lambda: refit_joint(model.de, model.ae, datasets, estimates, max_steps=3),
        )
    return {
        "n": n,
        "mode": mode,
        "recordings": len(datasets),
        "events_per_recording": len(datasets[0].events),
        "band_width": int(index.shape[1]),
        "seed_score": float(max(scores)) if scores else None,
        "round_best_score": float(report.best_score),
        "round_candidates": int(report.n_valid),
        "stages": figures,
    }


def table(results: list[dict]) -> str:
    stages = [*STAGES, *(s for s in POST_STAGES if any(s in r.get("stages", {}) for r in results))]
    head = "| n | mode | band | " + " | ".join(stages) + " | peak RSS |"
    rule = "|" + "---|" * (len(stages) + 4)
    rows = [head, rule]
    for r in results:
        if "error" in r:
            rows.append(f"| {r['n']} | {r['mode']} | - | " + "failed: " + r["error"][:80] + " |")
            continue
        cells = []
        for s in stages:
            if s not in r["stages"]:
                cells.append("-")
                continue
            f = r["stages"][s]
            cells.append(f"{f['seconds']:.2f} s, {f['tracemalloc_peak_mb']:.0f} MB")
        rss = max(f["maxrss_mb"] for f in r["stages"].values())
        rows.append(
            f"| {r['n']} | {r['mode']} | {r['band_width']} | "
            + " | ".join(cells)
            + f" | {rss:.0f} MB |"
        )
    return "\n".join(rows) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[1000, 10000])
    ap.add_argument("--mode", choices=("long", "fine"), default="long")
    ap.add_argument("--out", type=Path, default=Path("/tmp/jaxdmd-scale"))
    ap.add_argument("--timeout", type=float, default=1800.0, help="seconds per size")
    ap.add_argument(
        "--model", type=Path, default=None,
        help="a finished run's folder: also measure the state estimate and the joint refit",
    )  # fmt: skip
    ap.add_argument("--child", type=int, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    cache = args.out / "source.npz"
    if args.child is not None:
        print(json.dumps(child(cache, args.child, args.mode, args.model)))
        return
    source(cache)
    results = []
    for n in args.sizes:
        cmd = [
            sys.executable,
            __file__,
            "--child",
            str(n),
            "--mode",
            args.mode,
            "--out",
            str(args.out),
            *(["--model", str(args.model)] if args.model is not None else []),
        ]
        t_start = time.perf_counter()
        try:
            proc = subprocess.run(cmd, capture_output=True, text=True, timeout=args.timeout)
        except subprocess.TimeoutExpired:
            results.append({"n": n, "mode": args.mode, "error": f"timeout after {args.timeout} s"})
            continue
        if proc.returncode != 0:
            tail = proc.stderr.strip().splitlines()[-1:] or [f"exit {proc.returncode}"]
            results.append({"n": n, "mode": args.mode, "error": tail[0]})
        else:
            r = json.loads(proc.stdout.strip().splitlines()[-1])
            r["process_seconds"] = round(time.perf_counter() - t_start, 1)
            results.append(r)
        print(table(results[-1:]).splitlines()[-1], flush=True)
    report = {
        "command": " ".join([Path(sys.executable).name, *sys.argv]),
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count()},
        "results": results,
    }
    (args.out / "scale.json").write_text(json.dumps(report, indent=2) + "\n")
    (args.out / "scale.md").write_text(table(results))
    print(table(results))


if __name__ == "__main__":
    main()
