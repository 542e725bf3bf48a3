"""``jaxdmd simulate``: simulate the IEEE 39-bus benchmark and write a dataset."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import jax

from jaxdmd.grid.machines import MODEL_STATES, Exciter, Governor, MachineModel
from jaxdmd.grid.operating import nominal_operating_point, operating_points, opf_operating_point
from jaxdmd.grid.protocol import generator_dataset
from jaxdmd.grid.simulate import Fault, simulate


def add_simulate_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the ``simulate`` options to ``parser``."""
    g = parser.add_argument_group("simulation")
    g.add_argument("--out", required=True, help="output file (.npz, or .csv with a .json sidecar)")
    g.add_argument("--fault-bus", type=int, default=15, help="faulted bus (1-39), default 15")
    g.add_argument("--fault-on", type=float, default=1.0, help="fault time in s (default 1.0)")
    g.add_argument("--fault-off", type=float, default=1.1, help="clearing time in s (default 1.1)")
    g.add_argument("--fault-x", type=float, default=1e-4, help="fault reactance in pu (1e-4)")
    g.add_argument("--generator", type=int, default=31, help="generator bus 30-39 (default 31)")
    g.add_argument(
        "--model", default="psat-5.1", help=f"machine model: {', '.join(MODEL_STATES)} (psat-5.1)"
    )
    g.add_argument("--damping", type=float, default=0.0, help="damping D, pu on 100 MVA (0)")
    g.add_argument(
        "--saturation", type=float, nargs=2, metavar=("S10", "S12"), default=None,
        help="field saturation of e'_q: factors S(1.0) and S(1.2), each in [0, 1) (default none)",
    )  # fmt: skip
    g.add_argument("--exciter", action="store_true", help="add the first-order AVR")
    g.add_argument("--governor", action="store_true", help="add the droop governor")
    g.add_argument("--noise", type=float, default=0.0, help="state noise, share of range (0)")
    g.add_argument("--seed", type=int, default=0, help="seed of operating points and noise")
    g.add_argument(
        "--load-scale", type=float, default=None,
        help="scale all loads by this factor (OPF dispatch); default: the case-file point",
    )  # fmt: skip
    g.add_argument(
        "--operating-points", type=int, default=0,
        help="N > 0: N random OPF points (loads +-30%%), one file each (FILE_k.suffix)",
    )  # fmt: skip
    g.add_argument("--t-end", type=float, default=10.0, help="simulated time in s (10)")
    g.add_argument("--dt", type=float, default=0.01, help="output period in s (0.01)")


def run_simulate(args: argparse.Namespace) -> int:
    """Run the ``simulate`` subcommand; returns the exit code. Bad input raises ``ValueError``."""
    out = Path(args.out)
    if out.suffix not in (".npz", ".csv"):
        raise ValueError(f"--out must end in .npz or .csv, got {out}")
    model = MachineModel(
        name=args.model,
        damping=args.damping,
        saturation=tuple(args.saturation) if args.saturation else None,
        exciter=Exciter() if args.exciter else None,
        governor=Governor() if args.governor else None,
    )
    fault = Fault(bus=args.fault_bus, t_on=args.fault_on, t_off=args.fault_off, x=args.fault_x)
    from jaxdmd.grid.network import case39

    case39().gen_index(args.generator)
    n = int(args.operating_points or 0)
    if n > 0:
        ops = operating_points(n, args.seed)
        paths = [out.with_name(f"{out.stem}_{k}{out.suffix}") for k in range(n)]
    else:
        ops = (
            nominal_operating_point()
            if args.load_scale is None
            else opf_operating_point(float(args.load_scale))
        )
        paths = [out]
    res = simulate(ops, model, fault, t_end=args.t_end, dt=args.dt)
    key = jax.random.fold_in(jax.random.key(args.seed), 0x5EED)
    for k, path in enumerate(paths):
        ds = generator_dataset(
            res, args.generator, k if n > 0 else None, noise=args.noise,
            key=jax.random.fold_in(jax.random.fold_in(key, k), args.generator),
            label=f"case39 gen {args.generator}, {model.name}, fault bus {fault.bus}, point {k}",
        )  # fmt: skip
        path.parent.mkdir(parents=True, exist_ok=True)
        ds.save(path)
        print(f"wrote {path}", file=sys.stderr)
    return 0
