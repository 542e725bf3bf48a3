"""Speed of the IEEE 39-bus fault simulation (PSAT 5.1, bus-15 fault, 10 s, 1001 samples).

Prints one JSON line: compile time, wall time of one simulation after compilation (median of
``--repeats``), and the throughput over a batch of ``--batch`` OPF operating points, simulated
one after another as ``paper_protocol`` does. ``--vmap`` also times the vmapped batch: it gives
no speed-up here (a batch takes the union of its runs' steps) and jax 0.10.2's CPU runtime now
and then never signals its completion (a hang at 0 % CPU), so it is off by default.

    python benchmarks/simulate_speed.py [--batch 8] [--repeats 10] [--model psat-5.1] [--vmap]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time

import jax

import jaxdmd  # noqa: F401  (float64)
from jaxdmd.grid import nominal_operating_point, operating_points, simulate
from jaxdmd.grid.protocol import simulate_each


def _timed(fn):
    t0 = time.perf_counter()
    out = fn()
    jax.block_until_ready(out.x)
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--repeats", type=int, default=10)
    ap.add_argument("--model", default="psat-5.1")
    ap.add_argument("--fault-bus", type=int, default=15)
    ap.add_argument("--vmap", action="store_true", help="also time the vmapped batch")
    args = ap.parse_args()

    op = nominal_operating_point()
    run = lambda: simulate(op, args.model, args.fault_bus)  # noqa: E731
    first = _timed(run)
    times = [_timed(run) for _ in range(args.repeats)]
    single = statistics.median(times)

    ops = operating_points(args.batch, 0)
    run_b = lambda: simulate_each(ops, args.model, args.fault_bus)  # noqa: E731
    batch = statistics.median([_timed(run_b) for _ in range(3)])
    extra = {}
    if args.vmap:
        run_v = lambda: simulate(ops, args.model, args.fault_bus)  # noqa: E731
        first_v = _timed(run_v)
        vmapped = statistics.median([_timed(run_v) for _ in range(3)])
        extra = {
            "vmap_compile_s": round(first_v - vmapped, 3),
            "vmap_batch_run_s": round(vmapped, 4),
            "vmap_runs_per_s": round(args.batch / vmapped, 2),
        }
    print(
        json.dumps(
            {
                "benchmark": "simulate_speed",
                "model": args.model,
                "fault_bus": args.fault_bus,
                "t_end_s": 10.0,
                "samples": 1001,
                "compile_plus_first_run_s": round(first, 3),
                "compile_s": round(first - single, 3),
                "single_run_s": round(single, 4),
                "single_run_min_s": round(min(times), 4),
                "batch": args.batch,
                "batch_run_s": round(batch, 4),
                "batch_runs_per_s": round(args.batch / batch, 2),
                **extra,
                "cpus": os.cpu_count(),
                "jax": jax.__version__,
                "machine": platform.machine(),
            }
        )
    )


if __name__ == "__main__":
    main()
