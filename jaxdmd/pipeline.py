"""Discovery as a library: ``discover(train, test, config) -> Discovery``.

The paper's pipeline on recordings, in order:

1. the DE loop (:mod:`jaxdmd.search`) finds the state equations and the variables they need
   (:func:`jaxdmd.problems.de_problem`: estimated derivatives, matched to the estimator);
2. their parameters are refitted in the integral form (:func:`jaxdmd.refine.refit_integral`);
3. the states are estimated with the discovered state equations (a Kalman smoother,
   :func:`jaxdmd.refine.model_states`), and the AE loop finds the algebraic variables the DE loop
   brought in as functions of those states, the inputs and the boundary
   (:func:`jaxdmd.problems.ae_problem`);
4. the AE parameters are refitted for the noise the estimated states keep (bias-compensated least
   squares), then by maximum likelihood with the states unknown (:func:`jaxdmd.refine.refit_joint`).

Every choice is a field of :class:`DiscoveryConfig` (frozen, documented, defaults here); the
proposer is a part passed in (default: the built-in offline search). :class:`Discovery` holds the
equations and the loops' final states, and rolls the model out (:meth:`Discovery.simulate`,
:meth:`Discovery.score`); :meth:`Discovery.save` and :func:`load` write and read it.

The command line (``python -m jaxdmd.run``) only turns its arguments into a config, shows
progress and writes files; ``benchmarks/table1.py`` calls :func:`discover` as any user would.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Protocol

import equinox as eqx
import jax
import numpy as np

from jaxdmd import search, ties, workers
from jaxdmd.data import Dataset
from jaxdmd.estimate import StateEstimate, without_covariance
from jaxdmd.identities import (
    Identity,
    fitted_nmse,
    measured_identities,
    with_identities,
)
from jaxdmd.problems import ae_problem, de_problem
from jaxdmd.prompts import Contract, Variable
from jaxdmd.proposers import Proposer
from jaxdmd.refine import (
    HOLDS,
    joint_likelihood,
    model_states,
    refit_bias_compensated,
    refit_integral,
    refit_joint,
    refit_joint_products,
    sharpened_states,
    smoothed_states,
)
from jaxdmd.search import Equations, Problem, RoundReport, SearchConfig, SearchState
from jaxdmd.select import (
    SelectionConfig,
    front_lines,
    inclusion_frequency,
    pool,
    reference_free,
    select_algebraic,
    select_by_simulation,
    select_states_closed,
    simulation_nrmse,
    used_variables,
    weighted_by_recording,
)
from jaxdmd.simfit import refit_finalists, refit_task, simulated_structure

__all__ = [
    "Discovery",
    "DiscoveryConfig",
    "Judge",
    "Observer",
    "OfflineFactory",
    "ProposerFactory",
    "discover",
    "load",
    "loads",
    "resume_or_init",
    "run_loop",
]


# ----------------------------------------------------------------------------------------------
# configuration


@dataclass(frozen=True)
class DiscoveryConfig:
    """How :func:`discover` turns recordings into a model. Every field has a sentence.

    Attributes:
        search: the search of each loop (islands, prompts and samples per round, temperatures,
            round limit, stagnation rules; :class:`jaxdmd.search.SearchConfig`).
        derivatives: ``"estimated"``: the state derivatives are estimated from the noisy states
            by the default estimator (:func:`jaxdmd.data.differentiate`) and each prediction is
            smoothed like the estimate before the comparison (matched fitting); ``"given"``: the
            recordings' stored derivatives are exact (a simulator's) and fitted as they are.
        weighted: with estimated derivatives, weight each sample by the inverse of the noise the
            estimator passes there (generalised least squares; the paper weights all alike).
        integral_window: fit the state equations in the integral form over windows of this
            many seconds during the search (increments of the smoothed states instead of
            derivatives); None fits derivatives.
        de_gamma: the DE loop's score threshold of stopping and extension; None takes the
            search's gamma, divided by ten when the DE NMSE is weighted or integral (the true
            structure's NMSE lies below the paper's 0.01 there and the loop would stop before
            extension brings in what it lacks).
        ae_gamma: the same for the AE loop; None takes the search's gamma, divided by ten when
            the AE regressors are model-estimated states (the true structure's NMSE lies near
            1e-4 there).
        refit_window: refit the final state equations' parameters in the integral form over
            windows of this many seconds (no derivative estimate needed); None keeps the
            search's fit.
        algebraic: run the AE loop (close the algebraic variables the DE loop used).
        ae_states: the AE loop's regressors when the states are noisy: ``"model"`` estimates
            them with a Kalman smoother whose process model is the discovered state equations;
            ``"smoothed"`` with the generic derivative estimator's smoother.
        ae_bias_correction: refit the AE equations by bias-compensated least squares, correcting
            for the noise the estimated states keep (with estimated derivatives only).
        ae_joint: with ``ae_states="model"``, refit the AE equations by maximum likelihood with
            the states unknown (:func:`jaxdmd.refine.refit_joint`).
        ae_joint_steps: the joint refit's BFGS steps at most.
        searches: independent searches of the DE loop (PRNG keys folded from the DE key);
            their archives are pooled for the final choice, and each chosen term's share of
            the searches whose own final equations hold it is reported (the structure must not
            be an accident of one search path).
        jobs: how many processes discovery keeps busy at once (:mod:`jaxdmd.workers`; None:
            as many as this process has cores): the searches side by side, and beside the
            closed selection and the joint refit the refits that need neither. Each result is
            the same to the last bit however many run at once. Only the built-in offline
            proposer searches in other processes (a language model's proposer is one object
            that every loop shares).
        selection: how the final state equations are chosen among the archive's alternatives
            by how they simulate the training recordings (:mod:`jaxdmd.select`); None keeps
            the choice by cross-validated derivative error alone.
    """

    search: SearchConfig = field(default_factory=SearchConfig)
    derivatives: Literal["estimated", "given"] = "estimated"
    weighted: bool = True
    integral_window: float | None = None
    de_gamma: float | None = None
    ae_gamma: float | None = None
    refit_window: float | None = 0.5
    algebraic: bool = True
    ae_states: Literal["model", "smoothed"] = "model"
    ae_bias_correction: bool = True
    ae_joint: bool = True
    ae_joint_steps: int = 1000
    searches: int = 3
    jobs: int | None = None
    selection: SelectionConfig | None = field(default_factory=SelectionConfig)

    def __post_init__(self) -> None:
        if self.derivatives not in ("estimated", "given"):
            raise ValueError(
                f"derivatives must be 'estimated' or 'given', got {self.derivatives!r}"
            )
        if self.ae_states not in ("model", "smoothed"):
            raise ValueError(f"ae_states must be 'model' or 'smoothed', got {self.ae_states!r}")
        if self.searches < 1:
            raise ValueError(f"searches must be at least 1, got {self.searches}")
        if self.jobs is not None and self.jobs < 1:
            raise ValueError(f"jobs must be at least 1 or None, got {self.jobs}")
        for name in ("integral_window", "refit_window", "de_gamma", "ae_gamma"):
            value = getattr(self, name)
            if value is not None and not value > 0:
                raise ValueError(f"{name} must be positive or None, got {value}")

    @property
    def processes(self) -> int:
        """``jobs``, or the cores this process may use when it is None."""
        return workers.cores() if self.jobs is None else self.jobs

    @property
    def matched(self) -> bool:
        """Predictions are smoothed like the estimated derivatives (the derivative form)."""
        return self.derivatives == "estimated" and self.integral_window is None

    def de_search(self) -> SearchConfig:
        """The DE loop's search configuration (its gamma resolved, see ``de_gamma``)."""
        if self.de_gamma is not None:
            return dataclasses.replace(self.search, gamma=self.de_gamma)
        if self.integral_window or (self.matched and self.weighted):
            return dataclasses.replace(self.search, gamma=self.search.gamma / 10)
        return self.search

    def ae_search(self, model_estimated: bool) -> SearchConfig:
        """The AE loop's search configuration (its gamma resolved, see ``ae_gamma``)."""
        if self.ae_gamma is not None:
            return dataclasses.replace(self.search, gamma=self.ae_gamma)
        if model_estimated:
            return dataclasses.replace(self.search, gamma=self.search.gamma / 10)
        return self.search


# ----------------------------------------------------------------------------------------------
# parts passed in: the proposer per loop, and what wants to hear about progress


class ProposerFactory(Protocol):
    """Makes the proposer of one loop from its problem (``loop`` is ``"DE"`` or ``"AE"``)."""

    name: str

    def __call__(self, problem: Problem, loop: str) -> Proposer: ...


class OfflineFactory:
    """The built-in offline search for each loop's problem (it reads that loop's data).

    ``subset_size``: per loop, the largest subset of building blocks the offline proposer's
    "subset" edit tries (:class:`jaxdmd.proposers.offline.OfflineConfig`); the AE loop's
    regressors are estimated states and it gains from larger subsets. ``blocks``: the user's
    building blocks, joining the grammar's second tier (``OfflineConfig.blocks``).
    """

    name = "offline"

    def __init__(
        self, subset_size: Mapping[str, int] | None = None, blocks: Sequence[str] = ()
    ) -> None:
        self.subset_size = {"DE": 3, "AE": 4, **dict(subset_size or {})}
        self.blocks = tuple(blocks)

    def __call__(self, problem: Problem, loop: str = "DE") -> Proposer:
        from jaxdmd.proposers.offline import OfflineConfig, OfflineProposer

        config = OfflineConfig(blocks=self.blocks)
        if loop in self.subset_size:
            config = dataclasses.replace(config, subset_size=self.subset_size[loop])
        return OfflineProposer.for_problem(problem, config)


class _Fixed:
    """One proposer (a language model) for both loops."""

    def __init__(self, proposer: Proposer) -> None:
        self.proposer = proposer
        self.name = str(getattr(proposer, "name", "llm"))

    def __call__(self, problem: Problem, loop: str = "DE") -> Proposer:
        return self.proposer

    def stats(self) -> dict[str, object]:
        stats = getattr(self.proposer, "stats", None)
        return stats.as_dict() if stats is not None else {}


class Observer(Protocol):
    """What :func:`discover` reports while it works (the command line prints it)."""

    def loop_started(self, name: str, state: SearchState) -> None: ...

    def round(self, name: str, state: SearchState, report: RoundReport) -> None: ...

    def message(self, text: str) -> None: ...


class _Silent:
    def loop_started(self, name: str, state: SearchState) -> None:
        pass

    def round(self, name: str, state: SearchState, report: RoundReport) -> None:
        pass

    def message(self, text: str) -> None:
        pass


# ----------------------------------------------------------------------------------------------
# a loop, resumable


def run_loop(
    state: SearchState,
    proposer: Proposer,
    *,
    on_round: Callable[[SearchState, RoundReport], None] | None = None,
    checkpoint: str | Path | None = None,
) -> SearchState:
    """Run rounds until the search ends; write the state after each round if asked."""
    while not state.done:
        state, requests = search.prompts(state)
        samples = proposer.propose(requests)
        state, report = search.step(state, samples)
        if checkpoint is not None:
            search.write_json_atomic(checkpoint, search.state_to_dict(state))
        if on_round is not None:
            on_round(state, report)
    return state


def resume_or_init(
    problem: Problem,
    contract: Contract,
    key: jax.Array,
    config: SearchConfig,
    checkpoint: str | Path | None,
) -> SearchState:
    """The saved state if ``checkpoint`` exists, else a fresh one."""
    if checkpoint is not None and Path(checkpoint).exists():
        path = Path(checkpoint)
        try:
            data = json.loads(path.read_text())
            return search.state_from_dict(data, problem, config)
        except (ValueError, KeyError, TypeError) as err:
            raise ValueError(f"cannot resume from the checkpoint {path}: {err}") from None
    return search.init(problem, contract, key, config)


class _Locked:
    """An observer whose calls are serialised (the searches in worker processes report from
    threads of this process)."""

    def __init__(self, observer: Observer) -> None:
        self.observer = observer
        self._lock = threading.Lock()

    def loop_started(self, name: str, state: SearchState) -> None:
        with self._lock:
            self.observer.loop_started(name, state)

    def round(self, name: str, state: SearchState, report: RoundReport) -> None:
        with self._lock:
            self.observer.round(name, state, report)

    def message(self, text: str) -> None:
        with self._lock:
            self.observer.message(text)


def _search_task(
    problem: Problem, contract: Contract, key_data: np.ndarray, config: SearchConfig,
    checkpoint: Path | None, factory: ProposerFactory, floor: float, *,
    progress: Callable[[Any], None],
) -> tuple[dict[str, object], Equations]:  # fmt: skip
    """One DE search in a worker process (:func:`jaxdmd.workers.start`): its state after each
    round goes back as progress (and to ``checkpoint``); the result is its final state and its
    own choice (:func:`jaxdmd.search.final_equations` with ``floor``)."""
    key = jax.random.wrap_key_data(jax.numpy.asarray(key_data))
    state = resume_or_init(problem, contract, key, config, checkpoint)
    progress(("started", search.state_to_dict(state)))
    state = run_loop(
        state,
        factory(problem, "DE"),
        on_round=lambda s, r: progress(("round", search.state_to_dict(s), r)),
        checkpoint=checkpoint,
    )
    return search.state_to_dict(state), search.final_equations(state, floor=floor)


def _choice_task(
    state: dict[str, object], problem: Problem, config: SearchConfig, floor: float, *,
    progress: Callable[[Any], None],
) -> Equations:  # fmt: skip
    """A finished search's own choice (:func:`jaxdmd.search.final_equations` with ``floor``)
    in a worker process, from its state as :func:`jaxdmd.search.state_to_dict` wrote it."""
    return search.final_equations(search.state_from_dict(state, problem, config), floor=floor)


def _finished(checkpoint: Path | None) -> bool:
    """A search whose checkpoint says it is done (resuming it costs nothing here)."""
    try:
        return checkpoint is not None and bool(json.loads(checkpoint.read_text()).get("done"))
    except (OSError, ValueError, AttributeError):
        return False


def _searches_side_by_side(
    names: Sequence[str], keys: Sequence[jax.Array], problem: Problem, contract: Contract,
    config: SearchConfig, factory: ProposerFactory, folder: Path | None, observer: Observer,
    label: str, jobs: int, here: Callable[[str, jax.Array], SearchState], floor: float,
) -> tuple[list[SearchState], list[Equations]]:  # fmt: skip
    """The searches ``names`` (PRNG ``keys``) at most ``jobs`` at once: the first here
    (``here(name, key)``), ``jobs - 1`` of the others in worker processes, and those left
    here after the first. Their rounds are shown as they come; a search whose worker fails
    runs here afterwards, from its checkpoint. Returns their final states and each one's own
    choice (:func:`jaxdmd.search.final_equations` with ``floor``), made where the search ran;
    that of a search run here while another is still to run here is made meanwhile in a worker,
    started once the workers' searches are done and their cores free."""

    def checkpoint(name: str) -> Path | None:
        return None if folder is None else folder / f"{name.lower()}_state.json"

    def show(name: str) -> Callable[[Any], None]:
        def progress(message: Any) -> None:
            state = search.state_from_dict(message[1], problem, config)
            if message[0] == "started":
                observer.loop_started(f"{label}{name}", state)
            else:
                observer.round(f"{label}{name}", state, message[2])

        return progress

    def choose(state: SearchState) -> Equations:
        return search.final_equations(state, floor=floor)

    away = [i for i in range(1, len(names)) if not _finished(checkpoint(names[i]))][: jobs - 1]
    running: dict[int, workers.Worker] = {}
    choosing: dict[int, workers.Worker] = {}
    starters: list[threading.Thread] = []
    states: dict[int, SearchState] = {}
    choices: dict[int, Equations] = {}

    # the cores the choices' workers may take once the searches' workers are done: at most
    # jobs - 1 at once beside this process (resumed searches all end at once, and their
    # choices would otherwise all start together, each holding the problem)
    free = threading.Semaphore(max(jobs - 1, 1))
    ending = threading.Event()
    starting = threading.Lock()  # a choice's worker starts wholly before or after the ending

    def choose_when_free(i: int, task: tuple[Any, ...]) -> None:
        """Start search i's choice in a worker once the workers' searches are done (their
        cores are then free; before, it would slow the search running here) and fewer than
        ``jobs - 1`` other choices run in workers."""
        for worker in running.values():
            worker.wait()
        with free:
            with starting:
                if ending.is_set():  # this call is ending (it raised): start nothing more
                    return
                choosing[i] = workers.start(_choice_task, *task)
            choosing[i].wait()

    try:
        for i in away:
            running[i] = workers.start(
                _search_task, problem, contract, np.asarray(jax.random.key_data(keys[i])),
                config, checkpoint(names[i]), factory, floor, on_progress=show(names[i]),
            )  # fmt: skip
        local = [i for i in range(len(names)) if i not in running]
        for n, i in enumerate(local):
            states[i] = here(names[i], keys[i])
            if n + 1 < len(local):
                task = (search.state_to_dict(states[i]), problem, config, floor)
                starters.append(threading.Thread(target=choose_when_free, args=(i, task)))
                starters[-1].start()
            else:
                choices[i] = choose(states[i])
        for i, worker in running.items():
            try:
                state, choices[i] = worker.result()
                states[i] = search.state_from_dict(state, problem, config)
            except workers.WorkerError as err:
                observer.message(f"{names[i]}: its worker process failed ({err}); run here")
                states[i] = here(names[i], keys[i])
        for starter in starters:
            starter.join()
        for i, worker in choosing.items():
            with contextlib.suppress(workers.WorkerError):  # else made here below
                choices[i] = worker.result()
        for i in range(len(names)):
            if i not in choices:  # its worker failed or could not be started: the same choice
                choices[i] = choose(states[i])
    finally:
        with starting:
            ending.set()
        # every choice worker started is here now, and no other will start
        for worker in [*running.values(), *choosing.values()]:
            worker.stop()
        for starter in starters:
            starter.join()
    return [states[i] for i in range(len(names))], [choices[i] for i in range(len(names))]


# ----------------------------------------------------------------------------------------------
# the result


@dataclass(frozen=True)
class Discovery:
    """The discovered differential-algebraic model, the loops' final states and what each step
    of :func:`discover` did.

    Attributes:
        de: the state equations (the DE loop's result, parameters refitted).
        ae: the algebraic equations (None if the AE loop did not run).
        de_state, ae_state: the loops' final search states (None for a loaded model).
        report: per step, what was done (``"de"``, ``"ae"``: rounds, refits, state estimates,
            wall times; ``"ae_skipped"``; ``"llm"``); the JSON-ready part of ``summary.json``.
        physical: the physical-parameter section (:func:`jaxdmd.physical.discovery_section`:
            Markdown and its dict) when :func:`discover` made it ahead; else :meth:`save`
            makes it.
    """

    de: Equations
    ae: Equations | None = None
    de_state: SearchState | None = None
    ae_state: SearchState | None = None
    report: Mapping[str, Any] = field(default_factory=dict)
    physical: tuple[str, dict[str, Any]] | None = None

    def simulate(self, recording: Dataset, mode: Literal["dae", "de"] = "dae"):
        """Roll the model out on ``recording`` (:func:`jaxdmd.rollout.rollout`): from its first
        sample, its inputs and boundary played in (``"dae"``; the measured algebraic variables
        too with ``"de"``). Returns a :class:`jaxdmd.rollout.RolloutResult`."""
        from jaxdmd.rollout import rollout

        ae = self.ae if mode == "dae" else None
        return rollout(self.de, recording, ae=ae, mode=mode)

    def score(
        self, recordings: Sequence[Dataset], mode: Literal["dae", "de"] = "dae"
    ) -> dict[str, Any]:
        """Rollout metrics on each recording (:func:`jaxdmd.rollout.score`) and their mean over
        the recordings: ``{"recordings": [...], "mean": {metric: value}, "n_diverged": k,
        "n_far_off": j}`` (far off: diverged or a state's R^2 below -10)."""
        from jaxdmd.rollout import score

        states = tuple(self.de.contract.targets)
        scores = [score(self.simulate(ds, mode), ds, states=states) for ds in recordings]
        keys = scores[0]["full"]["mean"] if scores else {}
        mean = {k: float(np.mean([s["full"]["mean"][k] for s in scores])) for k in keys}
        return {
            "recordings": scores,
            "mean": mean,
            "n_diverged": sum(1 for s in scores if s.get("diverged")),
            "n_far_off": sum(1 for s in scores if s.get("far_off")),
        }

    def held_out(self, recordings: Sequence[Dataset]) -> dict[str, Any]:
        """Rollout metrics on held-out recordings, per state and mean over states and
        recordings: ``"de"`` (the measured algebraic variables played in) and, with algebraic
        equations, ``"dae"`` (only the inputs and the boundary played in). A rollout that
        diverges counts, with its errors inf."""
        from jaxdmd.report import rollout_summary

        out: dict[str, Any] = {}
        for mode in ("de", "dae") if self.ae is not None else ("de",):
            scores = self.score(recordings, mode=mode)["recordings"]  # type: ignore[arg-type]
            out[mode] = rollout_summary(scores)
        return out

    def module_source(self) -> str:
        """The model as a Python module: skeletons and their fitted parameters (``model.py``)."""
        parts = [
            '"""Model discovered by jaxdmd: state equations (DE) and algebraic equations (AE)."""',
            "",
            "import jax.numpy as jnp  # noqa: F401  (the skeletons may call jnp functions)",
            "",
            self.de.source.rstrip(),
            "",
            f"DE_PARAMS = {[float(x) for x in self.de.params]!r}",
            f"DE_TARGETS = {list(self.de.contract.targets)!r}",
        ]
        if self.ae is not None:
            parts += [
                "",
                self.ae.source.rstrip(),
                "",
                f"AE_PARAMS = {[float(x) for x in self.ae.params]!r}",
                f"AE_TARGETS = {list(self.ae.contract.targets)!r}",
            ]
        return "\n".join(parts) + "\n"

    def summary(self) -> dict[str, Any]:
        """The JSON-ready summary of the discovery (``summary.json`` less what the caller adds:
        the data's source, the settings, the total wall time)."""
        return dict(self.report)

    def save(self, directory: str | Path, summary: Mapping[str, Any] | None = None) -> Path:
        """Write ``model.py``, ``equations.md``, ``scores.png`` (when the loops' states are
        known) and ``summary.json`` (``summary``, default :meth:`summary`) into ``directory``."""
        from jaxdmd import physical, report

        out = Path(directory)
        out.mkdir(parents=True, exist_ok=True)
        (out / "model.py").write_text(self.module_source())
        section, parameters = self.physical or physical.discovery_section(self)
        (out / "equations.md").write_text(
            physical.with_section(report.equations_markdown(self), section)
        )
        loops = [(n, s) for n, s in (("DE", self.de_state), ("AE", self.ae_state)) if s]
        if loops:
            report.plot_scores(out / "scores.png", loops)
        summary = self.summary() if summary is None else summary
        search.write_json_atomic(
            out / "summary.json", {"physical_parameters": parameters, **summary}
        )
        return out


def load(path: str | Path) -> Discovery:
    """A :class:`Discovery` from a run's folder (its ``model.py``) or a ``model.py`` file.

    The module is read as text and its skeletons are checked and compiled like any model answer
    (nothing in it is executed); ``DE_PARAMS``, ``DE_TARGETS`` (and ``AE_...``) must be literals.
    The loaded model simulates and scores as the discovered one did; its search states are not
    kept (``de_state`` and ``ae_state`` are None).
    """
    path = Path(path)
    file = path / "model.py" if path.is_dir() else path
    if not file.exists():
        raise ValueError(f"no model found: {file} does not exist")
    return loads(file.read_text(), str(file))


def loads(text: str, file: str = "<model>") -> Discovery:
    """A :class:`Discovery` from the text of a ``model.py`` (:func:`load`; ``file`` names it
    in errors and in ``report["loaded_from"]``)."""
    import ast

    from jaxdmd.skeleton import SkeletonError

    try:
        tree = ast.parse(text, filename=str(file))
    except SyntaxError as err:
        raise ValueError(f"{file} is not Python: {err}") from None
    values: dict[str, Any] = {}
    functions: list[ast.FunctionDef] = []
    for node in tree.body:
        if isinstance(node, ast.FunctionDef):
            functions.append(node)
        elif isinstance(node, ast.Assign) and len(node.targets) == 1:
            target = node.targets[0]
            if isinstance(target, ast.Name):
                try:
                    values[target.id] = ast.literal_eval(node.value)
                except ValueError:
                    raise ValueError(
                        f"{file}: {target.id} must be a literal (line {node.lineno})"
                    ) from None
    for name in ("DE_PARAMS", "DE_TARGETS"):
        if name not in values:
            raise ValueError(f"{file} has no {name}: not a model written by jaxdmd")
    if not functions:
        raise ValueError(f"{file} defines no function")
    has_ae = "AE_PARAMS" in values and len(functions) > 1

    def equations(fdef: ast.FunctionDef, loop: str, targets: Sequence[str],
                  params: Sequence[float], states: Sequence[str]) -> Equations:  # fmt: skip
        source = ast.get_source_segment(text, fdef) or ""
        args = [a.arg for a in fdef.args.args[:-1]]
        state_vars = tuple(Variable(s, "state") for s in states)
        library = tuple(Variable(a, "algebraic") for a in args if a not in states)
        contract = Contract(
            loop="DE" if loop == "DE" else "AE",
            targets=tuple(targets),
            states=state_vars,
            library=library,
            function_name=fdef.name,
        )
        n = len(targets)
        eq = Equations(contract, source, tuple(float(x) for x in params), (np.nan,) * n, np.nan)
        try:
            eq.skeleton()  # checked and compiled now: a bad file fails here, with its reason
        except SkeletonError as err:
            raise ValueError(f"{file}: the function {fdef.name!r} is rejected: {err}") from None
        return eq

    de_targets = tuple(values["DE_TARGETS"])
    de_args = [a.arg for a in functions[0].args.args[:-1]]
    states = tuple(a for a in de_args if a in de_targets)
    de = equations(functions[0], "DE", de_targets, values["DE_PARAMS"], states)
    ae = None
    if has_ae:
        ae = equations(functions[1], "AE", values["AE_TARGETS"], values["AE_PARAMS"], states)
    return Discovery(de=de, ae=ae, report={"loaded_from": str(file)})


# ----------------------------------------------------------------------------------------------
# discovery


def _dropped_total(rounds: Iterable[tuple[tuple[str, int], ...]]) -> dict[str, int]:
    """The count per reason over ``rounds`` (each a round's (reason, count) pairs), most
    frequent first."""
    total: Counter[str] = Counter()
    for row in rounds:
        total.update(dict(row))
    return dict(sorted(total.items(), key=lambda kv: (-kv[1], kv[0])))


def dropped_summary(state: SearchState) -> dict[str, object]:
    """Why the loop's samples were dropped: the count per reason over all rounds
    (``"total"``, most frequent first) and per round (``"per_round"``, a mapping per round)."""
    return {
        "total": _dropped_total(state.dropped),
        "per_round": [dict(row) for row in state.dropped],
    }


def _loop_summary(
    state: SearchState, eq: Equations, seconds: float, refit: dict[str, object] | None = None
) -> dict[str, object]:
    out: dict[str, object] = {
        "rounds": state.iteration,
        "stop_reason": state.stop_reason,
        "best_score_history": list(state.history),
        # each equation's best loss in the archive at the end (what stopping looks at)
        "equation_best": dict(
            zip(state.contract.targets, (state.equation_best or [()])[-1], strict=False)
        ),
        "library": [{"name": n, "joined_round": r} for n, r in state.joined],
        "missing_measurements": list(state.missing),
        "dropped": dropped_summary(state),
        "targets": list(eq.contract.targets),
        "equations": eq.readable(),
        "source": eq.source,
        "params": list(eq.params),
        "nmse": dict(zip(eq.contract.targets, eq.losses, strict=True)),
        "score": eq.score,
        "wall_time_s": seconds,
    }
    if refit is not None:  # the parameters above were refitted; nmse/score are the search's
        out["refit"] = refit
    return out


def _said_reference(observer: Observer, loop: str, dropped: dict[str, list[str]]) -> None:
    """Tell the observer which summands of a loop's choice moved with the angle reference."""
    if dropped:
        observer.message(
            f"{loop} terms that move with the network's angle reference left out: "
            + "; ".join(f"{t}: {', '.join(terms)}" for t, terms in dropped.items())
        )


def _estimate_summary(estimates: Sequence[StateEstimate]) -> dict[str, object]:
    model = estimates[0].from_model
    out: dict[str, object] = {
        "estimate": "model" if model else "smoothed",
        "noise_variance": [e.noise for e in estimates],
        "posterior_sd": {
            s: float(np.sqrt(np.mean(np.concatenate([e.covariance[:, i, i] for e in estimates]))))
            for i, s in enumerate(estimates[0].states)
        },
    }
    if model:
        out["process_factor"] = estimates[0].process
    return out


def _factory(proposer: Proposer | ProposerFactory | None) -> ProposerFactory:
    if proposer is None:
        return OfflineFactory()
    if hasattr(proposer, "propose"):
        return _Fixed(proposer)  # type: ignore[arg-type]
    return proposer  # type: ignore[return-value]


def discover(
    train: Sequence[Dataset],
    test: Sequence[Dataset] = (),
    config: DiscoveryConfig | None = None,
    proposer: Proposer | ProposerFactory | None = None,
    *,
    key: jax.Array | None = None,
    checkpoints: str | Path | None = None,
    observer: Observer | None = None,
    label: str = "",
) -> Discovery:
    """Discover the state and algebraic equations of a component from its recordings.

    Args:
        train: the training recordings (:class:`jaxdmd.data.Dataset`; states, and the channels
            the equations may use). With ``config.derivatives == "estimated"`` their derivatives
            are (re-)estimated here by the default estimator.
        test: held-out recordings; the AE equations' R^2 on them goes into the report.
        config: :class:`DiscoveryConfig` (default: the paper's pipeline as jaxdmd runs it).
        proposer: a proposer used by both loops (e.g. a language model), a factory making one
            per loop, or None for the built-in offline search.
        key: the PRNG key of the whole discovery (default ``jax.random.key(0)``).
        checkpoints: a folder where each loop's state is written after every round; a loop
            found finished there is resumed, not rerun.
        observer: told about loops and rounds (progress display); default silent.
        label: prefixed to the loop names shown to the observer.

    Returns:
        A :class:`Discovery`.
    """
    config = config or DiscoveryConfig()
    observer = _Locked(observer or _Silent())  # searches in other processes report from threads
    factory = _factory(proposer)
    key = jax.random.key(0) if key is None else key
    train = list(train)
    if not train:
        raise ValueError("discover needs at least one training recording")
    estimated = config.derivatives == "estimated"
    if estimated:
        train = [ds.with_estimated_derivatives() for ds in train]
    weighted = config.matched and config.weighted
    integral = config.integral_window
    folder = None if checkpoints is None else Path(checkpoints)
    de_key, ae_key = jax.random.split(key)

    def run(
        name: str, problem: Problem, contract: Contract, key: jax.Array, cfg: SearchConfig
    ) -> SearchState:
        checkpoint = None if folder is None else folder / f"{name.lower()}_state.json"
        state = resume_or_init(problem, contract, key, cfg, checkpoint)
        observer.loop_started(f"{label}{name}", state)
        return run_loop(
            state,
            factory(problem, name.rstrip("0123456789")),
            on_round=lambda s, r: observer.round(f"{label}{name}", s, r),
            checkpoint=checkpoint,
        )

    def loop(
        name: str, problem: Problem, contract: Contract, key: jax.Array, cfg: SearchConfig,
        floor: float,
    ) -> tuple[SearchState, Equations, float]:  # fmt: skip
        start = time.perf_counter()
        state = run(name, problem, contract, key, cfg)
        return state, search.final_equations(state, floor=floor), time.perf_counter() - start

    # the DE loop: several independent searches, their archives pooled for the final choice
    start = time.perf_counter()
    de_problem_, de_contract = de_problem(
        train, matched=config.matched, weighted=weighted, integral=integral, smooth=bool(integral)
    )
    keys = [de_key, *(jax.random.fold_in(de_key, 100 + i) for i in range(1, config.searches))]
    names = ["DE" if i == 0 else f"DE{i + 1}" for i in range(config.searches)]
    jobs = config.processes
    # NMSEs of the integral form lie far below the derivatives': no absolute floor there
    floor = 0.0 if integral else 1e-4
    with workers.one_blas_thread():  # as in the worker processes: the same archives anywhere
        if jobs > 1 and len(keys) > 1 and isinstance(factory, OfflineFactory):
            de_states, per_search = _searches_side_by_side(
                names, keys, de_problem_, de_contract, config.de_search(), factory, folder,
                observer, label, jobs, lambda name, key: run(
                    name, de_problem_, de_contract, key, config.de_search()
                ), floor,
            )  # fmt: skip
        else:
            de_states = [
                run(name, de_problem_, de_contract, k, config.de_search())
                for name, k in zip(names, keys, strict=True)
            ]
            per_search = [search.final_equations(s, floor=floor) for s in de_states]
    de_state = pool(de_states)
    if len(de_states) > 1:  # the pool's choice; each search's own choice is a candidate
        de = search.final_equations(de_state, floor=floor, include=per_search)
    else:
        de = per_search[0]
    # no term that moves with the network's angle reference (a rotor angle alone)
    de, de_moving = reference_free(de_state, de)
    _said_reference(observer, "DE", de_moving)
    # every state equation's samples weighted by its error variance in their recording (a
    # recording whose machine slipped poles has states, currents and voltages tens of times
    # noisier than the others', and unweighted it bends the fit): what follows fits on it
    de_state, de, de_recording_weights = weighted_by_recording(de_state, de)
    de_seconds = time.perf_counter() - start
    selection = None
    if config.selection is not None:
        start = time.perf_counter()
        de, selection = select_by_simulation(de_state, de, train, config.selection)
        selection["seconds"] = time.perf_counter() - start
        de_seconds += selection["seconds"]
        if selection.get("changed"):
            observer.message(
                "DE equations chosen by simulation: "
                + ", ".join(f"d{t}/dt" for t in selection["changed"])  # type: ignore[union-attr]
            )
    judge = Judge(train, config.selection)
    refit = None
    if config.refit_window:
        refitted, refit_nmse = refit_integral(
            de, train, config.refit_window, jax.random.fold_in(de_key, 9)
        )
        nmse = dict(zip(de.contract.targets, refit_nmse, strict=True))
        refit = {"form": "integral", "window_s": config.refit_window, "nmse": nmse}
        de = judge.better(de, refitted, refit)
    report: dict[str, Any] = {
        "proposer": factory.name,
        "de": _loop_summary(de_state, de, de_seconds, refit),
    }
    if de_recording_weights:
        report["de"]["recording_weights"] = de_recording_weights
    if de_moving:
        report["de"]["reference_dropped"] = de_moving
    if selection is not None:
        report["de"]["selection"] = selection
    if len(de_states) > 1:
        report["de"]["searches"] = [
            {"rounds": st.iteration, "stop_reason": st.stop_reason, "equations": eq.readable(),
             "library": [{"name": n, "joined_round": r} for n, r in st.joined],
             "dropped": dropped_summary(st)}
            for st, eq in zip(de_states, per_search, strict=True)
        ]  # fmt: skip
        # over all searches; each search's rounds are under "searches"
        report["de"]["dropped"] = {
            "total": _dropped_total(row for st in de_states for row in st.dropped)
        }

    ae = ae_state = None
    ae_seconds = 0.0
    regressors: Sequence[Dataset] = train  # the recordings with the states estimated, if they are
    if not config.algebraic:
        report["ae_skipped"] = "--skip-ae"
    elif not any(v.role == "algebraic" for v in de.contract.library):
        report["ae_skipped"] = "the DE loop used no algebraic variable: there is nothing to close"
        observer.message(f"AE loop skipped: {report['ae_skipped']}")
    else:
        start = time.perf_counter()
        estimates = _ae_regressors(config, de, train, observer) if estimated else None
        regressors = train if estimates is None else [e.dataset for e in estimates]
        states_seconds = time.perf_counter() - start
        fine = estimates is not None and estimates[0].from_model
        states_summary = None if estimates is None else _estimate_summary(estimates)
        ae_state, ae, ae_seconds = loop(
            "AE", *ae_problem(regressors, de.contract), ae_key, config.ae_search(fine),
            floor=1e-5 if fine else 1e-4,
        )  # fmt: skip
        ae_seconds += states_seconds
        ae, ae_moving = reference_free(ae_state, ae)
        _said_reference(observer, "AE", ae_moving)
        sharpened = None
        if fine and config.ae_joint:
            # the states estimated again through the loop's lines that hold: what follows
            # (the choice of lines, their fits) reads these
            start = time.perf_counter()
            with workers.one_blas_thread():  # the same estimate however many cores
                sharper, sharpened = sharpened_states(
                    de, ae, train, estimates, max_steps=config.ae_joint_steps
                )
            sharpened["seconds"] = time.perf_counter() - start
            ae_seconds += sharpened["seconds"]
            if sharper is not None:
                estimates, regressors = sharper, [e.dataset for e in sharper]
                states_summary = _estimate_summary(estimates)
                ae_state = _with_states(ae_state, regressors, de.contract.targets)
                observer.message(
                    "States estimated again with the AE lines that hold: "
                    + ", ".join(sharpened["through"])
                )
            elif sharpened.get("together") or sharpened.get("left_out"):
                tried = {**sharpened.get("left_out", {}), **sharpened.get("together", {})}
                observer.message(
                    "States not estimated again with the AE lines that hold ("
                    + ", ".join(tried) + "): " + sharpened["kept"]
                )  # fmt: skip
        # every algebraic equation's samples weighted by its error variance in their recording
        # (estimated from the loop's choice): what follows fits on the reweighted problem
        weighted, ae, recording_weights = weighted_by_recording(ae_state, ae)
        weights = weighted.problem.weights if recording_weights else None
        ae_selection = refits_ahead = compensated = None
        fit_choice = ae
        if config.selection is not None:
            start = time.perf_counter()
            # where the closed model and the held-out fit cannot tell a simpler line from the
            # current one, the likelihood with the states unknown decides
            likelihood = (
                joint_likelihood(
                    de, train, estimates, max_steps=config.ae_joint_steps, jobs=jobs
                ) if fine and config.ae_joint and estimates is not None else None
            )  # fmt: skip
            ae, ae_selection = select_algebraic(
                weighted, ae, de, train, config.selection, played_from=regressors,
                likelihood=likelihood,
            )  # fmt: skip
            ae_selection["seconds"] = time.perf_counter() - start
            ae_seconds += ae_selection["seconds"]
            if ae_selection.get("changed"):
                observer.message(
                    "AE equations chosen by simulation: " + ", ".join(ae_selection["changed"])  # type: ignore[arg-type]
                )
            # the state equations chosen again, closed by the algebraic ones; with a second
            # core, the AE refits below start beside it in a worker for the state equations as
            # they are now, and are used if the closed selection keeps them
            if estimates is not None:  # the AE equations are chosen: their bias compensation
                compensated, estimates = _compensated(ae, estimates, weights, config)
            if fine and config.ae_joint and jobs > 1:
                observer.message(_JOINT_MESSAGE)
                task = (refit_algebraic, de, ae, train, estimates, compensated, config, weighted)
                refits_ahead = (de, workers.start(*task))
            start = time.perf_counter()
            starts = [front_lines(selection or {}, t) for t in de.contract.targets]
            de, closed = select_states_closed(
                de_state, de, weighted, ae, train, config.selection, regressors, starts
            )
            closed["seconds"] = time.perf_counter() - start
            de_seconds += closed["seconds"]
            report["de"]["closed_selection"] = closed
            if closed.get("changed"):
                report["de"]["params"] = list(de.params)
                report["de"]["equations"] = de.readable()
                observer.message(
                    "DE equations chosen again in the closed model: "
                    + ", ".join(f"d{t}/dt" for t in closed["changed"])  # type: ignore[union-attr]
                )
        # the loop's own choice is refitted by simulation with these state equations (below,
        # in refit_finalists) whatever the refits between do to the selection's parameters:
        # with a second core, that refit runs in a worker beside them
        ahead = {}
        if (
            config.selection is not None and jobs > 1 and ae_selection is not None
            and ae_selection.get("changed")
            and simulated_structure(de, fit_choice) != simulated_structure(de, ae)
        ):  # fmt: skip
            worker = workers.start(refit_task, de, fit_choice, train, regressors, config.selection)
            ahead["fit choice"] = worker.result
        bias_report = joint_report = None
        if estimates is not None:
            start = time.perf_counter()
            if refits_ahead is None and fine and config.ae_joint:
                observer.message(_JOINT_MESSAGE)
            if estimates[0].covariance is not None:  # not compensated above (no selection)
                compensated, estimates = _compensated(ae, estimates, weights, config)

            def refit_here() -> tuple[Equations, Any, Any]:
                with workers.one_blas_thread():  # as in the worker: the same refits either way
                    return refit_algebraic(de, ae, train, estimates, compensated, config, weighted)

            ae, bias_report, joint_report = _ahead_or_here(refits_ahead, de, refit_here, observer)
            ae_seconds += time.perf_counter() - start
            joint = joint_report or {}
            rebuilt = [t["target"] for t in joint.get("products", ()) if t.get("chosen")]
            if rebuilt:
                refused = not joint.get("products_kept", True)
                observer.message(
                    "AE equations rebuilt from products of those that hold (the joint likelihood "
                    "rose): " + ", ".join(dict.fromkeys(rebuilt))
                    + ("; not kept: the model then simulates the training recordings worse"
                       if refused else "")
                )  # fmt: skip
        jointly_fitted = ae.source  # the structure the joint refit judged (if it ran)
        simulation_report = None
        if config.selection is not None:
            held = "recordings" if len(train) > 1 else "time blocks"
            observer.message(f"AE and DE refit by simulation, checked on left-out {held} ...")
            de_before = de
            # the selection's lines and the loop's own choice each refitted by simulation: the
            # one that then simulates left-out data better is the model
            finalists = [("selected", ae)]
            if ae_selection is not None and ae_selection.get("changed"):
                finalists.append(("fit choice", fit_choice))
            with workers.one_blas_thread():  # as in the worker: the same refit either way
                de, ae, simulation_report = refit_finalists(
                    de, finalists, train, regressors, config.selection, ahead
                )
            ae_seconds += simulation_report["seconds"]
            if simulation_report["chosen"] != "selected":
                # the selection's changes are reported as not kept
                ae_selection["not_kept"] = ae_selection["changed"]  # type: ignore[index]
                ae_selection["changed"] = []  # type: ignore[index]
                observer.message(
                    "AE equations: the loop's own choice simulates left-out data better after "
                    "the simulation refit than the selection's; the selection is not kept"
                )
            if de is not de_before:  # the state equations' parameters changed with the AE's
                report["de"]["params"] = list(de.params)
                report["de"]["equations"] = de.readable()
                report["de"]["simulation_refit"] = "refitted with the AE equations (see ae)"
        summary = _loop_summary(ae_state, ae, ae_seconds)
        if recording_weights:
            summary["recording_weights"] = recording_weights
        if ae_moving:
            summary["reference_dropped"] = ae_moving
        if ae_selection is not None:
            summary["selection"] = ae_selection
        if bias_report is not None:  # "params"/"equations" are then the refitted ones
            summary["bias_compensated"] = bias_report
        if states_summary is not None:
            if sharpened is not None:
                states_summary["sharpened"] = sharpened
            summary["states"] = states_summary
        identities = measured_identities(weighted, ae)
        if joint_report is not None:  # "params"/"equations" are then the refitted ones
            summary["joint_refit"] = joint_report
        if simulation_report is not None:
            summary["simulation_refit"] = simulation_report
        holds = _holding(joint_report, ae.source == jointly_fitted)
        if holds is not None:
            summary["holds"] = holds
            if holds["not_holding"]:
                observer.message(
                    "AE equations that do not hold with the states unknown (their terms are "
                    "suspect): " + ", ".join(holds["not_holding"])
                )
        if identities:
            held = "held-out recordings" if len(train) > 1 else "the recording"
            observer.message(
                f"Relations among the algebraic measurements that fit their variable on {held} "
                "ten times better than its line in the states: "
                + "; ".join(f"{i.text(4)} (NMSE {i.errors_text()})" for i in identities)
            )
            ae, summary["identities"] = _identities_in_model(ae, identities, weighted, de, judge)
            written = [t for t, item in summary["identities"].items() if item["in_model"]]
            if written:
                summary.update(_equations_summary(ae))
                observer.message(
                    "AE equations written as those relations in the model's own lines (there "
                    "they fit their variable better than its line, and the closed model "
                    "simulates the training recordings no worse): " + ", ".join(written)
                )
        if test:
            from jaxdmd.rollout import algebraic_r2

            summary["test_r2"] = algebraic_r2(ae, list(test))
        report["ae"] = summary
    report["de"]["inclusion_frequency"] = inclusion_frequency(de, per_search)
    stats = getattr(factory, "stats", None)
    if stats is not None:
        report["llm"] = stats()
    report["wall_time_s"] = de_seconds + ae_seconds
    # with a second core and held-out recordings, the physical-parameter section (for save) is
    # made in a worker meanwhile: the held-out rollouts run here, where their compiled programs
    # serve the caller's plots
    problems = (de_state.problem, None if ae_state is None else ae_state.problem)
    physical = workers.start(_physical_task, de, ae, *problems) if jobs > 1 and test else None
    result = Discovery(de=de, ae=ae, de_state=de_state, ae_state=ae_state, report=report)
    report["modes"] = _modes(result, regressors)
    if test:
        report["test"] = result.held_out(test)
    if physical is not None:
        with contextlib.suppress(workers.WorkerError):  # if it failed, save() makes it here
            result = dataclasses.replace(result, physical=physical.result())
    return result


def _identities_in_model(
    ae: Equations,
    identities: Sequence[Identity],
    state: SearchState,
    de: Equations,
    judge: Judge,
) -> tuple[Equations, dict[str, dict[str, Any]]]:
    """Each relation among the measured algebraic variables written into the model in place of
    its variable's line (:func:`jaxdmd.identities.with_identities`), one at a time in the
    targets' order, where, written in the model's lines, it fits its variable on the AE problem
    better than the variable's own line does, both with the model's parameters as they are
    (:func:`jaxdmd.identities.fitted_nmse`: a relation exact on the measurements is only as
    good, in the model, as the lines it reads), and kept where the closed model then simulates
    the training recordings no worse (``judge``). Returns the equations and, per relation, its
    report with ``in_model``."""
    report: dict[str, dict[str, Any]] = {}
    kept: list[Identity] = []
    model = ae
    own = fitted_nmse(ae, state)
    targets = list(ae.contract.targets)
    for identity in identities:
        item = report[identity.target] = identity.as_dict()
        written = with_identities(ae, [*kept, identity], state)
        if written is None:
            item["in_model"] = False
            item["kept"] = (
                "it reads a variable written as a relation, or the equations with it exceed "
                "a skeleton's size limits"
            )
            continue
        j = targets.index(identity.target)
        item["model_fit_nmse"] = {"line": own[j], "relation": written.losses[j]}
        if not ties.settled(written.losses[j]) < ties.settled(own[j]):  # a tie: the line
            item["in_model"] = False
            item["kept"] = (
                "written in the model's lines it fits its variable no better than the "
                "variable's own line"
            )
            continue
        model = judge.better(model, written, item, de=de)
        item["in_model"] = model is written
        if item["in_model"]:
            kept.append(identity)
    return model, report


def _equations_summary(eq: Equations) -> dict[str, object]:
    """The keys of :func:`_loop_summary` that follow the equations (after a change to them)."""
    return {
        "equations": eq.readable(),
        "source": eq.source,
        "params": list(eq.params),
        "nmse": dict(zip(eq.contract.targets, eq.losses, strict=True)),
    }


def _holding(joint: dict[str, Any] | None, same_structure: bool) -> dict[str, Any] | None:
    """How well each final algebraic equation holds (``summary["ae"]["holds"]``): the joint
    refit's error shares (:data:`jaxdmd.refine.HOLDS`), if it ran and the final equations have
    the structure it fitted (whether or not its parameters were kept); else None."""
    if not joint or "error_share" not in joint or not same_structure:
        return None
    return {
        "error_share": joint["error_share"],
        "not_holding": joint["not_holding"],
        "bar": HOLDS,
    }


def _physical_task(
    de: Equations, ae: Equations | None, de_problem: Problem, ae_problem: Problem | None, *,
    progress: Callable[[Any], None],
) -> tuple[str, dict[str, Any]]:  # fmt: skip
    """The physical-parameter section (:func:`jaxdmd.physical.section`) in a worker process."""
    from jaxdmd import physical

    return physical.section(de, ae, de_problem, ae_problem)


def _modes(model: Discovery, recordings: Sequence[Dataset]) -> list[dict[str, Any]]:
    """The model's small-signal modes at each recording's first sample
    (:func:`jaxdmd.rollout.modes`: closed by the algebraic equations where there are, else with
    the measured algebraic variables held; an entry with ``error`` where that fails)."""
    from jaxdmd.rollout import modes

    mode = "dae" if model.ae is not None else "de"  # without AE: measured, held
    out: list[dict[str, Any]] = []
    for i, ds in enumerate(recordings):
        name = ds.label or f"#{i + 1}"
        try:
            out.append({"recording": name, **modes(model.de, ds, ae=model.ae, mode=mode)})
        except ValueError as err:
            out.append({"recording": name, "error": str(err)})
    return out


class Judge:
    """Keeps a refit only if the model simulates the training recordings at least as well
    with it (:func:`jaxdmd.select.simulation_nrmse`: the state equations with the measured
    algebraic variables played in, or, for algebraic equations, the closed model). A refit is
    a better estimator on paper; whether it is better for the user is what the simulation says.
    Without a selection config every refit is kept."""

    def __init__(self, train: Sequence[Dataset], config: SelectionConfig | None) -> None:
        self.train, self.config = list(train), config

    def better(
        self, before: Equations, after: Equations, report: dict, de: Equations | None = None
    ) -> Equations:
        if self.config is None or after is before:
            return after
        if de is None:
            errors = [
                simulation_nrmse(eq, self.train, config=self.config) for eq in (before, after)
            ]
        else:
            errors = [simulation_nrmse(de, self.train, eq, self.config) for eq in (before, after)]
        report["simulation_nrmse"] = {"before": errors[0], "after": errors[1]}
        if errors[1] <= errors[0]:
            return after
        report["kept"] = "the refit simulates the training recordings worse"
        return before


_JOINT_MESSAGE = "AE refit: maximum likelihood with the states unknown ..."


def _ahead_or_here(
    ahead: tuple[Equations, workers.Worker] | None,
    de: Equations,
    here: Callable[[], Any],
    observer: Observer,
) -> Any:
    """The result of work started ahead in a worker for the state equations ``ahead[0]``, if
    they are still ``de`` and the worker did not fail (said with a message); else ``here()``,
    the same work run here. A worker whose result is of no use is stopped."""
    if ahead is not None and ahead[0] == de:
        try:
            return ahead[1].result()
        except workers.WorkerError as err:
            observer.message(f"a worker failed ({err}); its work runs here")
    elif ahead is not None:  # started for state equations that the selection then changed
        ahead[1].stop()
    return here()


def compensated_algebraic(
    ae: Equations, estimates: Sequence[StateEstimate], weights: Any, config: DiscoveryConfig
) -> tuple[Equations, dict[str, str]] | None:
    """The AE equations refitted by bias-compensated least squares on the estimated states
    (:func:`jaxdmd.refine.refit_bias_compensated`; ``weights``: the problem's sample weights,
    None for none), with one BLAS thread, as :func:`refit_algebraic` runs everywhere; None if
    ``config.ae_bias_correction`` is off. The only refit that reads the states' covariances:
    it runs where they are, and :func:`refit_algebraic` judges its result."""
    if not config.ae_bias_correction:
        return None
    with workers.one_blas_thread():
        return refit_bias_compensated(ae, estimates, weights)


def _compensated(
    ae: Equations, estimates: Sequence[StateEstimate], weights: Any, config: DiscoveryConfig
) -> tuple[tuple[Equations, dict[str, str]] | None, list[StateEstimate]]:
    """:func:`compensated_algebraic`, and the estimates without their covariances, which
    nothing after it reads: at four recordings of 1e5 samples they are 80 MB that neither this
    process nor the refits' worker then holds."""
    return (
        compensated_algebraic(ae, estimates, weights, config),
        [without_covariance(e) for e in estimates],
    )


def refit_algebraic(
    de: Equations,
    ae: Equations,
    train: Sequence[Dataset],
    estimates: Sequence[StateEstimate],
    compensated: tuple[Equations, dict[str, str]] | None,
    config: DiscoveryConfig,
    state: SearchState | None = None,
    *,
    progress: Callable[[Any], None] | None = None,
) -> tuple[Equations, dict[str, Any] | None, dict[str, Any] | None]:
    """The AE equations refitted on the estimated states, each refit kept only if the model
    then simulates the training recordings no worse (:class:`Judge`): bias-compensated least
    squares (``compensated``: :func:`compensated_algebraic`'s result, None for none), then,
    with model-estimated states, maximum likelihood with the states unknown
    (``config.ae_joint``), and the lines that then do not hold and that the state equations
    use rebuilt from products of those that do, judged by the same likelihood
    (:func:`jaxdmd.refine.refit_joint_products`, given ``state``, the AE problem on the
    estimated states) and then, as every refit, by the training rollouts. What
    :func:`discover` runs once the state equations are chosen, here or in a worker process
    (``progress`` unused: the task signature of :mod:`jaxdmd.workers`). The states'
    covariances are not read: a worker is sent the estimates without them
    (:func:`jaxdmd.estimate.without_covariance`). Returns the equations and the two refits'
    reports (None: not run)."""
    judge = Judge(train, config.selection)
    bias_report = joint_report = None
    if compensated is not None:
        refitted, bias_report = compensated
        bias_report = dict(bias_report)  # the judge writes its verdict into the report
        ae = judge.better(ae, refitted, bias_report, de=de)
    if estimates[0].from_model and config.ae_joint:
        start = time.perf_counter()
        try:
            refitted, joint_report = refit_joint(
                de, ae, train, estimates, max_steps=config.ae_joint_steps
            )
            ae = judge.better(ae, refitted, joint_report, de=de)
            if state is not None and joint_report.get("not_holding"):
                first = joint_report
                other, joint_report = refit_joint_products(
                    de, refitted, joint_report, train, estimates, state,
                    variables=used_variables(de), max_steps=config.ae_joint_steps,
                )  # fmt: skip
                if other is not None:  # a rebuilt structure, judged as every refit is
                    verdict: dict[str, Any] = {}
                    if judge.better(ae, other, verdict, de=de) is other:
                        ae = other
                    else:  # the report stays the structure's that the model keeps
                        joint_report = dict(first, products=joint_report["products"])
                    joint_report["products_simulation_nrmse"] = verdict.get("simulation_nrmse")
                    joint_report["products_kept"] = ae is other
        except (ValueError, np.linalg.LinAlgError) as err:
            joint_report = {"kept": f"the joint refit failed: {err}"}
        joint_report["seconds"] = time.perf_counter() - start
    return ae, bias_report, joint_report


def _with_states(
    state: SearchState, datasets: Sequence[Dataset], states: Sequence[str]
) -> SearchState:
    """``state`` with its problem's state channels taken from ``datasets`` (the same
    recordings, their states estimated again)."""
    from jaxdmd.data import stack_samples

    stacked = stack_samples(list(datasets), tuple(states))
    variables = dict(state.problem.variables)
    variables.update({s: jax.numpy.asarray(stacked[s]) for s in states if s in variables})
    problem = eqx.tree_at(lambda p: p.variables, state.problem, variables)
    return search.replace_state(state, problem=problem)


def _ae_regressors(
    config: DiscoveryConfig, de: Equations, train: Sequence[Dataset], observer: Observer
) -> list[StateEstimate]:
    """The AE loop's regressors: the noisy states replaced by an estimate (``ae_states``); the
    Kalman smoother falls back to the generic one, with a message, if it fails."""
    if config.ae_states == "model":
        try:
            return model_states(de, train)
        except (ValueError, np.linalg.LinAlgError) as err:
            observer.message(
                f"state estimation with the DE model failed ({err}); "
                "the AE loop uses the smoothed states"
            )
    return smoothed_states(train, de.contract.targets)
