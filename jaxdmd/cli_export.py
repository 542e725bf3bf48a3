"""``jaxdmd export RUN_DIR``: a discovered model written for other simulators (arguments ->
:func:`jaxdmd.export.export` -> files)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from jaxdmd.export import FORMATS


def _formats(text: str) -> list[str]:
    names = [f.strip() for f in text.split(",") if f.strip()]
    bad = [f for f in names if f not in FORMATS]
    if bad or not names:
        raise argparse.ArgumentTypeError(
            f"unknown format(s) {bad or text!r}; a comma-separated list of {', '.join(FORMATS)}"
        )
    return names


def add_export_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "run", metavar="RUN_DIR", help="a discovery's output folder (its model.py) or a model.py"
    )
    parser.add_argument(
        "--format",
        type=_formats,
        default=list(FORMATS),
        help="comma-separated: dyr (PSS/E record), andes (ANDES JSON case, a single machine on "
        "an infinite bus), py (jaxdmd's module, any structure); default: all",
    )
    parser.add_argument(
        "--out", default=None, help="output folder (default: RUN_DIR/export)", metavar="DIR"
    )
    parser.add_argument(
        "--data",
        nargs="*",
        metavar="FILE",
        help="fit the standard records to training recordings: the standard model fitted as a "
        "whole (its parameters tied as its family ties them; also written as "
        "standard_model.py); with no FILE, to the run's own (read from RUN_DIR/run.json: its "
        "files, or the benchmark simulated again); without --data the records hold the values "
        "read off the discovered lines",
    )
    parser.add_argument("--bus", type=int, default=1, help="the .dyr record's bus number")
    parser.add_argument("--id", default="1", help="the .dyr record's machine id")
    parser.add_argument("--p0", type=float, default=0.8, help="ANDES case: active power (pu)")
    parser.add_argument("--v0", type=float, default=1.0, help="ANDES case: terminal voltage (pu)")
    parser.add_argument(
        "--x-line", type=float, default=0.3, help="ANDES case: line reactance to the infinite bus"
    )
    from jaxdmd.cli_data import add_role_arguments

    add_role_arguments(
        parser.add_argument_group(
            "channel roles (of the --data columns: for a CSV without a sidecar, or to override it)"
        )
    )


def run_recordings(run: Path) -> list:
    """The training recordings of the discovery in ``run`` (its ``run.json``: the data files
    with the roles it was given, or the benchmark simulated again with its generator, operating
    points, noise and seed)."""
    import json

    from jaxdmd.report import Progress
    from jaxdmd.run import RUN_KEYS, parse_args, recordings

    try:
        saved = json.loads((run / "run.json").read_text())
    except (OSError, ValueError) as err:
        raise ValueError(
            f"--data without files needs the run's {run / 'run.json'} ({err}); give the files"
        ) from None
    args = parse_args(["discover"])
    for key in RUN_KEYS:
        setattr(args, key, saved.get(key, getattr(args, key)))
    train, _, _ = recordings(args, Progress())
    return train


def _fit_line(fit: dict) -> str:
    """One line on the standard model's fit (:func:`jaxdmd.export.fit_standard`'s report)."""
    if "why" in fit:
        return f"standard records read off the discovered lines: {fit['why']}"
    loro = fit.get("loro", {})
    errors = (
        f" (left-out simulation NRMSE {loro['refit']:.4g}; fitted by least squares, in sample: "
        f"{loro['given']:.4g})"
        if "refit" in loro and "given" in loro
        else ""
    )
    how = (
        f"standard model fitted as a whole to the recordings{errors}"
        if fit["from"] == "refit"
        else f"standard model fitted by least squares (the refit by simulation was not kept: "
        f"{fit.get('kept')})"
    )
    return how + (f"; projected on PSAT 5.1: {fit['projected']}" if "projected" in fit else "")


def run_export(args: argparse.Namespace) -> int:
    from jaxdmd.export import export
    from jaxdmd.pipeline import load

    discovery = load(args.run)
    run = Path(args.run)
    out = Path(args.out) if args.out else (run if run.is_dir() else run.parent) / "export"
    andes = {"p0": args.p0, "v0": args.v0, "x_line": args.x_line}
    fitted_to = None
    if args.data:
        from jaxdmd.cli_diagnose import load_recordings

        fitted_to = load_recordings(args.data, args)
    elif args.data is not None:  # --data alone: the run's own training recordings
        fitted_to = run_recordings(run if run.is_dir() else run.parent)
    written = export(
        discovery, out, args.format, bus=args.bus, machine_id=args.id, andes=andes,
        fitted_to=fitted_to,
    )  # fmt: skip
    fit = written.pop("standard_fit", None)
    if fit is not None:
        print(_fit_line(fit))
    if "standard_model" in written:
        print(f"standard model: {written.pop('standard_model')}")
    failed = 0
    for fmt, what in written.items():
        if isinstance(what, Path):
            print(f"{fmt}: {what}")
        else:
            failed += 1
            print(f"{fmt}: not written: {what}", file=sys.stderr)
    return 2 if failed == len(written) else (1 if failed else 0)
