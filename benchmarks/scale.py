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

With ``--discover`` the stages are not run; instead the whole default discovery
(``jaxdmd.pipeline.discover`` with ``DiscoveryConfig()``: the three DE searches side by side,
the choice by simulation, the refits, the state estimate, the AE loop and the joint refit) runs
on the four recordings, and its memory is the peak of the whole process tree (this process and
its search workers, sampled every 0.25 s from ``/proc``: the sum of their resident sets, and of
their proportional sets, which count a page shared by k processes as 1/k in each). ``--rounds
R`` and ``--joint-steps S`` cap the searches' rounds and the joint refit's BFGS steps (their
defaults 15 and 1000): every stage still runs, on the same arrays, only fewer times, so the
peak is the default's while the time is a fraction of it. The searches' states are written to
``--out/checkpoints/<n>/`` after every round; a rerun into the same ``--out`` resumes them (as
finished, once they are), so a change to what follows the searches is measured without them.

Two ways to make n samples from the 10 s runs (``--mode``):

  long  the 0.01 s step kept, the run repeated end to end (with its fault events) until n
        samples: 1e5 samples are 1000 s. The estimator's band width stays 31 samples, so every
        stage should be linear in n. Each copy starts at the first run's pre-fault state, so
        the states jump at the joins (by up to their whole range: the governor and exciter
        take the machine elsewhere in 10 s); the joins are events (the derivatives are
        estimated piecewise between them), and a rollout over the whole recording still
        crosses them. (The benchmark's grid cannot simply be simulated for 1000 s instead: it
        loses synchronism within 100 s at three of the four operating points.) Before
        2026-11-29 the joins were not events;
  fine  10 s kept, the run interpolated (linearly) to n samples: the band width grows like n
        (the windows are fixed in seconds), so the band stages grow like n^2 however built.

Per stage: wall time, the peak of NumPy/Python allocations (tracemalloc, which also slows
Python-heavy code a little) and the process's peak RSS after the stage (ru_maxrss: JAX's
buffers included, monotone). Writes ``scale.json`` and ``scale.md`` (a table) to ``--out``.

    python benchmarks/scale.py --sizes 1000 10000 100000 [--mode long|fine] [--out DIR]
                               [--model runs/demo]
    python benchmarks/scale.py --sizes 100000 --discover [--rounds 6 --joint-steps 3] [--jobs 1]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import threading
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
            # each copy starts where the first run did, not where the last one ended: the
            # states jump there (by up to their whole range), so each join is an event too
            events = tuple(
                e
                for k in range(copies)
                for e in ((k * period,) if k else ()) + tuple(e0 + k * period for e0 in ev0)
                if e < t[-1]
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


def _tree(root: int) -> list[int]:
    """``root`` and every process below it (read from /proc)."""
    parents: dict[int, list[int]] = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as f:
                ppid = int(f.read().rsplit(")", 1)[1].split()[1])
        except (OSError, IndexError, ValueError):
            continue
        parents.setdefault(ppid, []).append(int(entry))
    out, todo = [], [root]
    while todo:
        pid = todo.pop()
        out.append(pid)
        todo.extend(parents.get(pid, ()))
    return out


def _kib(pid: int, path: str, field: str) -> int:
    try:
        with open(f"/proc/{pid}/{path}") as f:
            for line in f:
                if line.startswith(field):
                    return int(line.split()[1])
    except OSError:
        pass
    return 0


class TreeMemory:
    """The peak over time of the memory of this process and its children, sampled in a thread:
    the sum of their resident sets (VmRSS) and of their proportional sets (Pss)."""

    def __init__(self, every: float = 0.25) -> None:
        self.every, self.rss_mb, self.pss_mb, self.processes = every, 0.0, 0.0, 1
        self.window_mb = self.last_mb = 0.0  # the peak PSS since window() was last called; now
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self._stop.is_set():
            pids = _tree(os.getpid())
            rss = sum(_kib(p, "status", "VmRSS:") for p in pids) / 1024
            pss = sum(_kib(p, "smaps_rollup", "Pss:") for p in pids) / 1024
            self.rss_mb, self.pss_mb = max(self.rss_mb, rss), max(self.pss_mb, pss)
            self.window_mb, self.last_mb = max(self.window_mb, pss), pss
            self.processes = max(self.processes, len(pids))
            self._stop.wait(self.every)

    def window(self) -> float:
        """The peak PSS since the last call (then starts a new window): the last sample if
        none was taken since."""
        peak, self.window_mb = max(self.window_mb, self.last_mb), 0.0
        return peak

    def __enter__(self) -> TreeMemory:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()


class _Progress:
    """The discovery's loops and rounds on stderr, each with the time since the start."""

    def __init__(self, memory: TreeMemory) -> None:
        self.start, self.memory, self.rounds = time.perf_counter(), memory, 0
        self.timeline: list[tuple[float, float, str]] = []  # (seconds, peak PSS MB, what ended)

    def _say(self, text: str) -> None:
        elapsed = time.perf_counter() - self.start
        window = self.memory.window()
        self.timeline.append((round(elapsed, 1), round(window, 1), text))
        print(
            f"[{elapsed:7.1f} s, peak {window:.0f} MB since the last line] {text}",
            file=sys.stderr,
            flush=True,
        )

    def loop_started(self, name, state) -> None:
        self._say(f"{name} started")

    def round(self, name, state, report) -> None:
        self.rounds += 1
        self._say(f"{name} round {report.round}: best {report.best_score:.4g}")

    def message(self, text: str) -> None:
        self._say(text)


def discover_child(
    cache: Path, n: int, mode: str, rounds: int | None, joint_steps: int | None,
    jobs: int | None = None, checkpoints: Path | None = None,
) -> dict:  # fmt: skip
    """The whole default discovery on four recordings of n samples; its time and the peak
    memory of the process tree. ``checkpoints``: the searches' states (resumed if there)."""
    import dataclasses

    import jax

    from jaxdmd.pipeline import DiscoveryConfig, discover

    datasets = recordings(cache, n, mode)
    config = DiscoveryConfig()
    if rounds is not None:
        config = dataclasses.replace(
            config, search=dataclasses.replace(config.search, max_rounds=rounds)
        )
    if joint_steps is not None:
        config = dataclasses.replace(config, ae_joint_steps=joint_steps)
    if jobs is not None:
        config = dataclasses.replace(config, jobs=jobs)
    with TreeMemory() as memory:
        progress = _Progress(memory)
        t_start = time.perf_counter()
        model = discover(
            datasets, config=config, key=jax.random.key(0), observer=progress,
            checkpoints=checkpoints,
        )  # fmt: skip
        seconds = time.perf_counter() - t_start
        progress.message("discovery done")
    return {
        "n": n,
        "mode": mode,
        "recordings": len(datasets),
        "events_per_recording": len(datasets[0].events),
        "max_rounds": config.search.max_rounds,
        "joint_steps": config.ae_joint_steps,
        "searches": config.searches,
        "jobs": config.processes,
        "rounds_run": progress.rounds,
        "seconds": round(seconds, 1),
        "tree_peak_rss_mb": round(memory.rss_mb, 1),
        "tree_peak_pss_mb": round(memory.pss_mb, 1),
        "processes": memory.processes,
        "self_maxrss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
        "timeline": progress.timeline,
        "report_seconds": _seconds(model.report),
        "equations": {
            "de": model.de.readable(),
            "ae": None if model.ae is None else model.ae.readable(),
        },
    }


def _seconds(report: object, path: str = "") -> dict[str, float]:
    """Every wall time in the discovery's report (keys holding "seconds"), by its path."""
    out: dict[str, float] = {}
    if isinstance(report, dict):
        for k, v in report.items():
            where = f"{path}.{k}" if path else str(k)
            if "seconds" in str(k) and isinstance(v, int | float):
                out[where] = round(float(v), 1)
            else:
                out.update(_seconds(v, where))
    return out


def discover_table(results: list[dict]) -> str:
    rows = [
        "| n | recordings | round limit | rounds run | joint steps | jobs | processes | time "
        "| peak PSS (tree) | peak RSS (tree) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        if "error" in r:
            rows.append(f"| {r['n']} | failed: {r['error'][:80]} |")
            continue
        rows.append(
            f"| {r['n']} | {r['recordings']} | {r['max_rounds']} | {r['rounds_run']} "
            f"| {r['joint_steps']} | {r['jobs']} | {r['processes']} | {r['seconds']:.0f} s "
            f"| **{r['tree_peak_pss_mb']:.0f} MB** | {r['tree_peak_rss_mb']:.0f} MB |"
        )
    return "\n".join(rows) + "\n"


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
    ap.add_argument(
        "--discover", action="store_true",
        help="run the whole default discovery instead of the stages (memory of the process tree)",
    )  # fmt: skip
    ap.add_argument("--rounds", type=int, default=None, help="with --discover: round limit")
    ap.add_argument(
        "--joint-steps", type=int, default=None, help="with --discover: the joint refit's steps"
    )
    ap.add_argument(
        "--jobs", type=int, default=None,
        help="with --discover: processes at once (default: the cores, as discover's default)",
    )  # fmt: skip
    ap.add_argument("--child", type=int, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    render = discover_table if args.discover else table
    args.out.mkdir(parents=True, exist_ok=True)
    cache = args.out / "source.npz"
    if args.child is not None:
        from jaxdmd.workers import map_large_blocks

        map_large_blocks()  # as the command line does
        if args.discover:
            result = discover_child(
                cache, args.child, args.mode, args.rounds, args.joint_steps, args.jobs,
                args.out / "checkpoints" / str(args.child),
            )  # fmt: skip
        else:
            result = child(cache, args.child, args.mode, args.model)
        print(json.dumps(result))
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
            *(["--discover"] if args.discover else []),
            *(["--rounds", str(args.rounds)] if args.rounds is not None else []),
            *(["--joint-steps", str(args.joint_steps)] if args.joint_steps is not None else []),
            *(["--jobs", str(args.jobs)] if args.jobs is not None else []),
        ]
        t_start = time.perf_counter()
        try:
            # the child's progress (stderr) goes to the terminal; its result is its last line
            proc = subprocess.run(
                cmd, stdout=subprocess.PIPE, stderr=None, text=True, timeout=args.timeout
            )
        except subprocess.TimeoutExpired:
            results.append({"n": n, "mode": args.mode, "error": f"timeout after {args.timeout} s"})
            continue
        if proc.returncode != 0:
            results.append({"n": n, "mode": args.mode, "error": f"exit {proc.returncode}"})
        else:
            r = json.loads(proc.stdout.strip().splitlines()[-1])
            r["process_seconds"] = round(time.perf_counter() - t_start, 1)
            results.append(r)
        print(render(results[-1:]).splitlines()[-1], flush=True)
    report = {
        "command": " ".join([Path(sys.executable).name, *sys.argv]),
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count()},
        "results": results,
    }
    (args.out / "scale.json").write_text(json.dumps(report, indent=2) + "\n")
    (args.out / "scale.md").write_text(render(results))
    print(render(results))


if __name__ == "__main__":
    main()
