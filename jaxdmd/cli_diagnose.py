"""``jaxdmd diagnose``: what a model gets wrong on a recording, why, and the
extended model (arguments -> :func:`jaxdmd.diagnose.diagnose` -> report files)."""

from __future__ import annotations

import argparse
from collections.abc import Sequence

import jax

from jaxdmd.data import Dataset
from jaxdmd.report import Progress


def load_recordings(paths: Sequence[str], args: argparse.Namespace | None = None) -> list[Dataset]:
    """The recordings, with the roles of the role flags and the events of ``--events``
    (`jaxdmd.cli_data.load_data`)."""
    from jaxdmd.cli_data import load_data, role_flags

    if args is None or not (role_flags(args) or getattr(args, "events", None) is not None):
        return [Dataset.load(p) for p in paths]
    return load_data(paths, args)


def add_diagnose_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--data", nargs="+", required=True, metavar="FILE", help="recordings to fit and extend on"
    )
    parser.add_argument(
        "--model",
        required=True,
        help="a skeleton file (.py, with optional PARAMS and TARGETS) or a built-in model: "
        "classical, one-axis, two-axis, psat-5.1",
    )
    parser.add_argument(
        "--test-data",
        nargs="+",
        metavar="FILE",
        help="held-out recordings (default: the last --data recording, or the last 30 %% of a "
        "single one)",
    )
    parser.add_argument("--out", default="runs/diagnose", help="output folder")
    parser.add_argument(
        "--rounds", type=int, default=8, help="round limit of the extension search (0: none)"
    )
    parser.add_argument(
        "--window",
        type=float,
        default=3.0,
        help="integration window in s of the weak form the equations are compared in "
        "(0: compare derivatives, estimated from the states)",
    )
    parser.add_argument(
        "--threshold",
        type=float,
        default=0.2,
        help="share of an equation's held-out residual one term must explain to call the "
        "model structurally wrong",
    )
    parser.add_argument(
        "--seed", type=int, default=0, help="seed of the extension search's PRNG key (0)"
    )
    parser.add_argument(
        "--frequency",
        type=float,
        default=60.0,
        help="system frequency in Hz (terminal-channel diagnosis: Omega_b, and omega = f / "
        "frequency from a channel f)",
    )
    from jaxdmd.cli_data import add_role_arguments

    add_role_arguments(
        parser.add_argument_group(
            "channel roles (of the --data columns: for a CSV without a sidecar, or to override it)"
        )
    )


def run_diagnose(args: argparse.Namespace) -> int:
    from jaxdmd.diagnose import DiagnoseConfig, diagnose, load_model
    from jaxdmd.report import write_report

    progress = Progress()
    train = load_recordings(args.data, args)
    test = load_recordings(args.test_data, args) if args.test_data else None
    first = train[0]
    family = _terminal_family(args.model, first)
    if family is not None:
        return _run_terminal(args, family, train, test, progress)
    model = load_model(args.model, states=first.state_names, channels=first.names)
    window = args.window if args.window > 0 else None
    if window is None:
        train = [ds.with_estimated_derivatives() for ds in train]
    config = DiagnoseConfig(threshold=args.threshold, rounds=args.rounds, window=window)
    progress.console.print(
        f"Diagnosing [bold]{model.name}[/bold] (d/dt of {', '.join(model.targets)}) on "
        f"{len(train)} recording(s)..."
    )
    result = diagnose(
        train,
        model,
        test=test,
        key=jax.random.key(args.seed),
        config=config,
        on_round=lambda s, r: progress.round("extension", s, r),
    )
    path = write_report(args.out, result)
    c = result.cause
    for a in result.assumptions:
        progress.console.print(f"\n[bold]Not measured[/bold]: {a}")
    progress.console.print(f"\n[bold]Cause ({c.kind})[/bold]: {c.summary}")
    if result.extended is not None:
        from jaxdmd import pretty

        e = result.extended
        for target, rhs in zip(e.contract.targets, e.readable().values(), strict=True):
            progress.console.print(f"  {pretty.equation(target, rhs)}", markup=False)
    before = result.metrics.get("given", result.metrics["refit"])["nrmse"]
    after = result.metrics.get("extended", result.metrics["refit"])["nrmse"]
    progress.console.print(
        f"held-out error (NRMSE) {before:.3g} -> {after:.3g} ({result.gain:.1f}x); report: {path}"
    )
    return 0


def _terminal_family(spec: str, first: Dataset) -> str | None:
    """The built-in model to diagnose from terminal channels, when the data call for it (they
    have V, theta, P, Q and lack the model's rotor angle or internal voltages)."""
    from jaxdmd.diagnose import is_model_file
    from jaxdmd.grid.machines import canonical_model_name
    from jaxdmd.terminal import FAMILIES, is_terminal

    if is_model_file(spec):
        return None
    try:
        name = canonical_model_name(spec)
    except ValueError:
        return None
    return name if is_terminal(first, FAMILIES[name].states) else None


def _run_terminal(
    args: argparse.Namespace,
    family: str,
    train: list[Dataset],
    test: list[Dataset] | None,
    progress: Progress,
) -> int:
    from jaxdmd.terminal import TerminalConfig, diagnose_terminal, write_terminal_report

    progress.console.print(
        f"Diagnosing [bold]{family}[/bold] from terminal channels on {len(train)} "
        "recording(s): V and theta played in, P, Q (and omega) compared; rotor angle and "
        "internal voltages estimated..."
    )
    config = TerminalConfig(threshold=args.threshold, frequency=args.frequency)
    result = diagnose_terminal(
        train,
        family,
        test=test,
        config=config,
        progress=lambda line: progress.console.print(line, markup=False),
    )
    path = write_terminal_report(args.out, result)
    for a in result.assumptions:
        progress.console.print(f"\n[bold]Not measured[/bold]: {a}")
    progress.console.print(
        f"\n[bold]Cause ({result.cause['kind']})[/bold]: {result.cause['summary']}"
    )
    progress.console.print(f"report: {path}")
    return 0
