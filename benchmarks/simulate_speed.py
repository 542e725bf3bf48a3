"""Speed of the IEEE 39-bus fault simulation (PSAT 5.1, bus-15 fault, 10 s, 1001 samples).

Prints one JSON line: compile time, wall time of one simulation after compilation (median of
``--repeats``), and the throughput of a vmapped batch of ``--batch`` OPF operating points.

    python benchmarks/simulate_speed.py [--batch 8] [--repeats 10] [--model psat-5.1]
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
    args = ap.parse_args()

    op = nominal_operating_point()
    run = lambda: simulate(op, args.model, args.fault_bus)  # noqa: E731
    first = _timed(run)
    times = [_timed(run) for _ in range(args.repeats)]
    single = statistics.median(times)

    ops = operating_points(args.batch, 0)
    run_b = lambda: simulate(ops, args.model, args.fault_bus)  # noqa: E731
    first_b = _timed(run_b)
    times_b = [_timed(run_b) for _ in range(max(3, args.repeats // 3))]
    batch = statistics.median(times_b)
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
                "batch_compile_s": round(first_b - batch, 3),
                "batch_run_s": round(batch, 4),
                "batch_runs_per_s": round(args.batch / batch, 2),
                "cpus": os.cpu_count(),
                "jax": jax.__version__,
                "machine": platform.machine(),
            }
        )
    )


if __name__ == "__main__":
    main()
