"""Table I's jaxdmd rows again after a change to what follows the searches, without the searches.

A change to the choice by simulation, the refits or the closure leaves every search of a Table I
run as it was, and its checkpoints (``seed<S>/runs/gen<G>/{de,de2,de3,ae}_state.json``) hold the
searches' final states. This script copies each pair's checkpoints from a finished run
(``--from``), runs ``jaxdmd.pipeline.discover`` with Table I's defaults on the same recordings
(the searches resume as finished, everything after them runs with the code as it is now) and
compares the full DAE and the DE rows on the test fault with the run's:

    python benchmarks/reselect.py --from /tmp/t1f --out /tmp/rs --jobs 2
    python benchmarks/reselect.py --from /tmp/t1f --out /tmp/rs --seeds 0 --generators 31 32

A pair's outputs are written as ``python -m jaxdmd.run`` writes them (``--out/seed<S>/gen<G>/``,
``summary.json`` included); finished pairs are skipped on a rerun. At the end a Markdown table
(per pair: MAPE and R^2 before and after, P_e's test R^2, the algebraic lines the selection
changed) and the means per seed go to the terminal and ``--out/reselect.md``. A change to the
searches themselves (the proposer, the archive, the grammar) needs the full ``table1.py``.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import table1

GENERATORS = tuple(range(30, 40))


def run_pair(source: Path, out: Path, gen: int, seed: int) -> None:
    """One pair's discovery from ``source``'s checkpoints into ``out`` (in this process)."""
    import jax

    from jaxdmd import pipeline
    from jaxdmd.grid import benchmark_protocol

    out.mkdir(parents=True, exist_ok=True)
    for state in sorted(source.glob("*_state.json")):
        shutil.copy(state, out / state.name)
    data = benchmark_protocol([gen], 4, 0.01, seed)
    config = table1.discovery_config(
        table1.build_parser().parse_args(["--out", str(out), "--seed", str(seed)])
    )
    result = pipeline.discover(
        data.train[gen], data.test[gen], config, key=jax.random.key(seed), checkpoints=out
    )
    result.save(out, {"source": {"benchmark": "ieee39-psat-5.1", "generator": gen},
                      **result.report})  # fmt: skip


def compare(before: Path, after: Path, pairs: Sequence[tuple[int, int]]) -> str:
    """The Markdown comparison of the pairs finished in ``after`` with ``before``'s rows."""
    lines = [
        "| seed | generator | DAE MAPE % before | after | DAE R^2 before | after "
        "| DE MAPE % before | after | P_e test R^2 before | after | AE lines changed |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    per_seed: dict[int, list[tuple[float, float, float, float]]] = {}
    for gen, seed in pairs:
        summary = after / f"seed{seed}" / f"gen{gen}" / "summary.json"
        if not summary.exists():
            continue
        new = json.loads(summary.read_text())
        rows = json.loads((before / f"seed{seed}/generators/gen{gen}.json").read_text())["rows"]
        old = json.loads((before / f"seed{seed}/runs/gen{gen}/summary.json").read_text())
        dae, de = new["test"]["dae"]["mean"], new["test"]["de"]["mean"]
        pe = (old["ae"]["test_r2"].get("P_e", float("nan")),
              new["ae"]["test_r2"].get("P_e", float("nan")))  # fmt: skip
        selection = new["ae"].get("selection", {})
        changed = ", ".join(selection.get("changed", [])) or "-"
        if selection.get("not_kept"):  # the loop's own choice won after the simulation refit
            changed = f"fit choice kept ({', '.join(selection['not_kept'])} not)"
        lines.append(
            f"| {seed} | {gen} | {rows['jaxdmd_dae']['mape']:.3f} | {dae['mape']:.3f} "
            f"| {rows['jaxdmd_dae']['r2']:.3f} | {dae['r2']:.3f} "
            f"| {rows['jaxdmd_de']['mape']:.3f} | {de['mape']:.3f} "
            f"| {pe[0]:.4f} | {pe[1]:.4f} | {changed} |"
        )
        per_seed.setdefault(seed, []).append(
            (rows["jaxdmd_dae"]["mape"], dae["mape"], rows["jaxdmd_dae"]["r2"], dae["r2"])
        )
    lines.append("")
    everything: list[tuple[float, float, float, float]] = []
    for seed, values in sorted(per_seed.items()):
        everything += values
        lines.append(_means(f"seed {seed}", values))
    if len(per_seed) > 1:
        lines.append(_means("pooled", everything))
    return "\n".join(lines) + "\n"


def _means(label: str, values: Sequence[tuple[float, float, float, float]]) -> str:
    mean = [statistics.mean(v[i] for v in values) for i in range(4)]
    above = [sum(v[i] > 1.0 for v in values) for i in (0, 1)]
    return (
        f"- {label} ({len(values)} pairs): full DAE mean MAPE {mean[0]:.3f} % -> {mean[1]:.3f} %, "
        f"R^2 {mean[2]:.3f} -> {mean[3]:.3f}; pairs above 1 %: {above[0]} -> {above[1]}"
    )


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--from", dest="source", type=Path, required=True,
                        help="a finished table1.py --seeds run")  # fmt: skip
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--generators", type=int, nargs="+", default=list(GENERATORS))
    parser.add_argument("--jobs", type=int, default=1, help="pairs at a time (processes)")
    parser.add_argument("--worker", nargs=2, type=int, metavar=("GEN", "SEED"),
                        help=argparse.SUPPRESS)  # fmt: skip
    args = parser.parse_args(argv)
    if args.worker:
        gen, seed = args.worker
        run_pair(args.source / f"seed{seed}/runs/gen{gen}", args.out / f"seed{seed}/gen{gen}",
                 gen, seed)  # fmt: skip
        return 0
    pairs = [(g, s) for s in args.seeds for g in args.generators]
    missing = [p for p in pairs if not (args.source / f"seed{p[1]}/runs/gen{p[0]}").is_dir()]
    if missing:
        parser.error(f"{args.source} has no checkpoints for (generator, seed) {missing}")
    todo = [p for p in pairs if not (args.out / f"seed{p[1]}/gen{p[0]}/summary.json").exists()]
    env = table1.child_environment(dict(os.environ), args.jobs)

    def work(pair: tuple[int, int]) -> None:
        gen, seed = pair
        log = args.out / f"seed{seed}" / f"gen{gen}.log"
        log.parent.mkdir(parents=True, exist_ok=True)
        cmd = [sys.executable, __file__, "--from", str(args.source), "--out", str(args.out),
               "--worker", str(gen), str(seed)]  # fmt: skip
        with log.open("w") as handle:
            code = subprocess.call(cmd, stdout=handle, stderr=subprocess.STDOUT, env=env)
        print(f"(gen {gen}, seed {seed}) {'done' if code == 0 else f'failed, see {log}'}",
              flush=True)  # fmt: skip

    with ThreadPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        list(pool.map(work, todo))
    text = compare(args.source, args.out, pairs)
    (args.out / "reselect.md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
