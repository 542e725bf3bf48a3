"""``jaxdmd`` (also ``python -m jaxdmd``, ``python -m jaxdmd.run``): the command line
(arguments -> config -> call -> files). Subcommands ``discover``, ``simulate``, ``diagnose``,
``export``.

Without a subcommand it is ``discover``; with no arguments at all it runs the built-in benchmark
(the paper's protocol on the IEEE 39-bus system, generator at bus 31) with the offline proposer:
:func:`jaxdmd.pipeline.discover` (the DE loop, then the AE loop), and writes the discovered
model, the score trajectories and ``summary.json`` into the output folder (schema in
``docs/run.md``), with ``run.log`` (the progress lines). ``simulate`` writes a benchmark dataset
(:mod:`jaxdmd.grid.cli`), ``diagnose`` explains a model's error (:mod:`jaxdmd.cli_diagnose`),
``export`` writes a run's model for PSS/E, ANDES or as a module (:mod:`jaxdmd.cli_export`);
see ``jaxdmd --help``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path

import jax

from jaxdmd import pretty, search, workers
from jaxdmd.cli_data import ROLE_KEYS
from jaxdmd.pipeline import DiscoveryConfig, OfflineFactory, discover
from jaxdmd.report import Progress
from jaxdmd.search import SearchConfig

DEFAULT_OUT = "runs/latest"


COMMANDS = ("discover", "simulate", "diagnose", "export")


def build_parser() -> argparse.ArgumentParser:
    """The ``jaxdmd`` parser: the subcommands ``discover``, ``simulate``, ``diagnose`` and
    ``export``."""
    from jaxdmd.cli_diagnose import add_diagnose_arguments
    from jaxdmd.cli_export import add_export_arguments
    from jaxdmd.grid.cli import add_simulate_arguments

    parser = argparse.ArgumentParser(
        prog="jaxdmd",
        description="Discover dynamic models of power-system generators from measured data.",
        epilog=(
            "Without a subcommand: discover (python -m jaxdmd.run [--out DIR ...] as before; "
            "with no arguments at all, the built-in IEEE 39-bus benchmark). "
            "'jaxdmd COMMAND --help' lists a command's options."
        ),
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    disc = sub.add_parser(
        "discover",
        usage="%(prog)s [--out DIR] [--data FILE ...] [--test-data FILE ...] [options]\n"
        "       %(prog)s --resume DIR",
        help="discover a model from recordings (default: the built-in benchmark)",
        description=(
            "Discover the dynamic model of a power-system component from measured data: the DE "
            "loop (state equations), then the AE loop (algebraic ones). Without --data, on the "
            "built-in IEEE 39-bus benchmark with the offline proposer. Writes model.py, "
            "equations.md, summary.json, run.log and plots into --out (docs/run.md)."
        ),
    )
    add_discover_arguments(disc)
    sim = sub.add_parser(
        "simulate",
        help="simulate the IEEE 39-bus benchmark, write a dataset",
        description="Simulate a fault on the IEEE 39-bus system and write one generator's "
        "recording (.npz, or .csv with a .json sidecar).",
    )
    add_simulate_arguments(sim)
    diag = sub.add_parser(
        "diagnose",
        help="what a model gets wrong on a recording, why, and the extended model",
        description=(
            "Simulate MODEL on held-out data, name the cause of its error (the equation, a "
            "missing variable or term, or wrong parameters), extend it with the search and "
            "measure the gain. Writes report.md, diagnosis.json and plots (docs/diagnose.md)."
        ),
    )
    add_diagnose_arguments(diag)
    exp = sub.add_parser(
        "export",
        help="write a discovered model as a PSS/E record, an ANDES case or a Python module",
        description=(
            "Write the model of RUN_DIR (its model.py) for other simulators: the PSS/E .dyr "
            "record and the ANDES case of the standard machine model it maps to (GENCLS, "
            "GENSAL, GENROU; assumptions stated in the files), or, for any structure, jaxdmd's "
            "Python module, which jaxdmd.load(path).simulate(recording) rolls out."
        ),
    )
    add_export_arguments(exp)
    return parser


def with_command(argv: Sequence[str]) -> list[str]:
    """``argv`` with ``discover`` put first when it names no subcommand (the old form:
    ``python -m jaxdmd.run [--out DIR ...]``); top-level ``-h``/``--help`` are kept."""
    argv = list(argv)
    if argv and (argv[0] in COMMANDS or argv[0] in ("-h", "--help")):
        return argv
    return ["discover", *argv]


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    """Parse a command line (default ``sys.argv[1:]``); no subcommand means ``discover``."""
    return build_parser().parse_args(with_command(sys.argv[1:] if argv is None else argv))


# fmt: off
def add_discover_arguments(parser: argparse.ArgumentParser) -> None:
    """The discovery options: what a user sets first, then the algorithm's internals."""
    g = parser.add_argument_group("discovery")
    add = g.add_argument
    add("--out", metavar="DIR", default=None, help=f"output folder (default {DEFAULT_OUT})")
    add("--data", nargs="+", metavar="FILE",
        help="training recordings (.npz, or .csv or COMTRADE .cfg with a .json sidecar or the "
        "role flags); default: the benchmark")
    add("--test-data", nargs="+", metavar="FILE", help="held-out recordings")
    add("--given-derivatives", action="store_true",
        help="fit the derivatives stored in --data as they are (exact ones, from a simulator); "
        "by default they are re-estimated from the states and the fit is matched to the "
        "estimator's smoothing")
    add("--time", action="store_true",
        help="offer the time since each recording's start as an input (unit s): for a forcing "
        "that depends on time, sin(w t) and cos(w t) with w fitted; leave it out for an "
        "autonomous component")
    add("--generator", type=int, default=31, help="benchmark generator bus (30-39)")
    add("--operating-points", type=int, default=4, help="benchmark training points")
    add("--noise", type=float, default=0.01, help="benchmark noise (share of range)")
    add("--rounds", type=int, default=15, help="round limit of each loop")
    add("--seed", type=int, default=0,
        help="seed of the search's PRNG key (and of the benchmark's operating points and noise)")
    add("--skip-ae", action="store_true", help="run the DE loop only")
    add("--resume", metavar="DIR", help="continue the run saved in DIR")
    from jaxdmd.cli_data import add_role_arguments

    add_role_arguments(parser.add_argument_group(
        "channel roles (of the --data columns: for a CSV without a sidecar, or to override it)"
    ))
    from jaxdmd.proposers.llm import add_llm_arguments

    add_llm_arguments(parser)
    g = parser.add_argument_group("advanced (the search and the refits; see docs/run.md)")
    add = g.add_argument
    add("--prompts", type=int, default=4, help="prompts per round")
    add("--samples", type=int, default=4, help="samples per prompt")
    add("--islands", type=int, default=10,
        help="islands of the archive: sub-populations of candidate models kept apart")
    add("--tau-c", type=float, default=0.2, help="cluster temperature")
    add("--tau-l", type=float, default=0.2, help="code-length temperature")
    add("--no-recombine", action="store_true",
        help="do not offer the per-equation recombination of the best lines each round")
    add("--integral", type=float, default=None, metavar="SECONDS",
        help="fit the state equations in their integral form over windows of this length "
        "during the search (DiscoveryConfig.integral_window)")
    add("--weighted", action=argparse.BooleanOptionalAction, default=True,
        help="weight the DE samples by the inverse noise of the derivative estimates")
    add("--refit-integral", type=float, default=0.5, metavar="SECONDS",
        help="refit the final state equations in the integral form over windows of this "
        "length (0: keep the search's fit)")
    add("--ae-bias-correction", action=argparse.BooleanOptionalAction, default=True,
        help="refit the AE equations by bias-compensated least squares")
    add("--ae-states", choices=("model", "smoothed"), default="model",
        help="the AE loop's regressors: states estimated with the discovered state equations "
        "(a Kalman smoother) or by the generic smoother")
    add("--ae-joint", action=argparse.BooleanOptionalAction, default=True,
        help="refit the AE equations by maximum likelihood with the states unknown")
    add("--ae-joint-steps", type=int, default=1000, help="BFGS steps of the joint refit at most")
    add("--subset-de", type=int, default=3,
        help="offline proposer: largest subset of building blocks of its 'subset' edit (DE)")
    add("--subset-ae", type=int, default=4, help="... and in the AE loop")
    add("--gamma", type=float, default=None,
        help="score threshold of stopping and extension (default: DiscoveryConfig's)")
# fmt: on


# ----------------------------------------------------------------------------------------------
# arguments -> config


def config_from_args(args: argparse.Namespace) -> DiscoveryConfig:
    """The :class:`DiscoveryConfig` the discovery options ask for."""
    return DiscoveryConfig(
        search=SearchConfig(
            n_islands=args.islands,
            prompts_per_round=args.prompts,
            samples_per_prompt=args.samples,
            tau_c=args.tau_c,
            tau_l=args.tau_l,
            max_rounds=args.rounds,
            recombine=not args.no_recombine,
        ),
        derivatives="given" if args.data and args.given_derivatives else "estimated",
        weighted=args.weighted,
        integral_window=args.integral,
        de_gamma=args.gamma,
        ae_gamma=args.gamma,
        refit_window=args.refit_integral or None,
        algebraic=not args.skip_ae,
        ae_states=args.ae_states,
        ae_bias_correction=args.ae_bias_correction,
        ae_joint=args.ae_joint,
        ae_joint_steps=args.ae_joint_steps,
    )


def proposer_from_args(args: argparse.Namespace):
    """The language model the options ask for, else the offline search (its subset sizes)."""
    from jaxdmd.proposers.llm import proposer_from_args as llm

    return llm(args) or OfflineFactory({"DE": args.subset_de, "AE": args.subset_ae})


RUN_KEYS = (
    "data", "test_data", "given_derivatives", "time", "generator", "operating_points", "noise",
    "rounds", "prompts", "samples", "islands", "tau_c", "tau_l", "seed", "no_recombine", "weighted",
    "skip_ae", "integral", "gamma", "refit_integral", "ae_bias_correction", "ae_states",
    "ae_joint", "subset_de", "subset_ae", *ROLE_KEYS,
)  # fmt: skip
"""The options a run records in run.json (and ``--resume`` restores)."""


def restore(args: argparse.Namespace, saved: dict) -> None:
    """``args`` with a run's recorded options (``run.json``); an option it does not record (a
    newer one) keeps its default."""
    for k in RUN_KEYS:
        setattr(args, k, saved.get(k, getattr(args, k)))


# ----------------------------------------------------------------------------------------------
# the discovery command


def recordings(
    args: argparse.Namespace, progress: Progress, jobs: int = 1
) -> tuple[list, Sequence, dict]:
    """Training and test recordings (files, or the benchmark's simulation) and their source."""
    if args.data:
        from jaxdmd.cli_data import load_data

        train = load_data(args.data, args)
        test = load_data(args.test_data, args) if args.test_data else []
        if args.time:
            train, test = [ds.with_time() for ds in train], [ds.with_time() for ds in test]
        return train, test, {"data": args.data, "test_data": args.test_data or []}
    from jaxdmd.grid import benchmark_protocol

    progress.message(
        f"Simulating the benchmark: generator {args.generator}, "
        f"{args.operating_points} operating points, bus-15 fault (train), bus-28 (test)..."
    )
    g = args.generator
    source = {"benchmark": "ieee39-psat-5.1", "generator": g}
    if jobs == 1:
        data = benchmark_protocol((g,), args.operating_points, args.noise, args.seed)
        return list(data.train[g]), list(data.test[g]), source
    # the test recordings, needed at the end, simulated in a worker meanwhile (the same ones)
    task = (g, args.operating_points, args.noise, args.seed)
    worker = workers.start(benchmark_test, *task, on_progress=_warn_again)
    data = benchmark_protocol((g,), args.operating_points, args.noise, args.seed, ("train",))
    test = workers.Later(worker, lambda: benchmark_test(*task, progress=_warn_again))
    return list(data.train[g]), test, source


def benchmark_test(
    generator: int, points: int, noise: float, seed: int, *, progress: Callable[[str], None]
) -> list:
    """The benchmark's test recordings of one generator (a worker's task): a warning, such as
    a machine out of step, goes to ``progress``."""
    from jaxdmd.grid import benchmark_protocol

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        data = benchmark_protocol((generator,), points, noise, seed, ("test",))
    for w in caught:
        progress(str(w.message))
    return list(data.test[generator])


def _warn_again(text: str) -> None:
    """A worker's warning, issued here."""
    from jaxdmd.grid.simulate import SynchronismWarning

    warnings.warn(text, SynchronismWarning, stacklevel=2)


def run_discover(args: argparse.Namespace) -> int:
    if args.resume:
        out = Path(args.resume)
        try:
            saved = json.loads((out / "run.json").read_text())
        except (OSError, ValueError) as err:
            raise ValueError(f"cannot resume from {out / 'run.json'}: {err}") from None
        restore(args, saved)
    else:
        out = Path(args.out or DEFAULT_OUT)
    progress = Progress()
    t0 = time.perf_counter()
    config = config_from_args(args)
    proposer = proposer_from_args(args)
    train, test, source = recordings(args, progress, config.processes)  # read before writing
    data_seconds = time.perf_counter() - t0
    if not args.resume:
        out.mkdir(parents=True, exist_ok=True)
        search.write_json_atomic(out / "run.json", {k: getattr(args, k) for k in RUN_KEYS})
    progress.log_to(out / "run.log")  # the lines shown so far too; a resumed run appends
    try:
        result = discover(
            train, test, config, proposer,
            key=jax.random.key(args.seed), checkpoints=out, observer=progress,
        )  # fmt: skip
        report = dict(result.report)
        settings = {k: getattr(args, k) for k in RUN_KEYS}
        summary = {"source": source, "proposer": report.pop("proposer"), "settings": settings}
        summary.update(report)
        summary["data_wall_time_s"] = data_seconds
        summary["wall_time_s"] = time.perf_counter() - t0
        result.save(out, summary)
        progress.print(f"\n[bold]Discovered model[/bold] (written to {out}/):")
        for eq in (result.de, result.ae):
            if eq is None:
                continue
            rhs = eq.readable(by_name=True).values()
            for target, v in zip(eq.contract.targets, rhs, strict=True):
                text = pretty.equation(target, v, dt=eq.contract.loop == "DE")
                progress.print(f"  {text}", markup=False)
        if test:
            from jaxdmd.report import plot_trajectories, rollout_table

            progress.print(f"\n[bold]Held-out rollouts[/bold] ({len(test)} recording(s)):")
            progress.print(rollout_table(result.report["test"]), markup=False)
            modes = ("de", "dae") if result.ae is not None else ("de",)
            sims = {m.upper(): result.simulate(test[0], m) for m in modes}  # type: ignore[arg-type]
            plot_trajectories(out / "trajectories.png", test[0], sims)
    finally:
        progress.close()
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    import logging

    from jaxdmd.proposers.llm import LLMError

    logging.getLogger("httpx").setLevel(logging.WARNING)
    args = parse_args(argv)
    workers.map_large_blocks()  # this process is the command line's
    try:
        if args.command == "simulate":
            from jaxdmd.grid.cli import run_simulate

            return run_simulate(args)
        if args.command == "diagnose":
            from jaxdmd.cli_diagnose import run_diagnose

            return run_diagnose(args)
        if args.command == "export":
            from jaxdmd.cli_export import run_export

            return run_export(args)
        return run_discover(args)
    except KeyboardInterrupt:
        print("interrupted; continue with --resume", file=sys.stderr)
        return 130
    except (LLMError, ValueError, OSError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
