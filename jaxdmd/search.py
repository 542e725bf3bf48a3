"""The search: a pure state, ``prompts(state)`` and ``step(state, samples)``.

One round of LLM-DMD (paper, Sec. III) is

    state, requests = prompts(state)          # in-context examples drawn from the islands
    samples = proposer.propose(requests)      # the only part that may talk to the world
    state, report = step(state, samples)      # check, compile, fit in one batch, register

``step`` is pure and deterministic given the state (its PRNG key included): it parses and checks
the samples, compiles them, fits the whole batch in one call, registers the results in the island
archive, records the best score, and applies the paper's rules:

- variable extension when the search stagnates: the best-score gain stayed <= epsilon for R
  rounds (since the last extension) and some equation's best loss is >= gamma (an exact
  equation must not mask the others). The JSON variable requests of the top-k skeletons are
  read; a requested variable the data holds joins the variable library; one it lacks is
  reported as a measurement to add;
- termination when every equation's best loss (over the archive: what the recombination of the
  best lines reaches) stays below gamma for R rounds and none of them halved over those R
  rounds, or after ``max_rounds``
  (plus up to R rounds when a variable joined the library in the last R rounds: the round
  limit does not bind before a late variable had its chance).

Beyond the paper, each round also offers one recombined candidate: the best line of every
equation, taken from whichever candidates hold them (the equations are separable).
"""

from __future__ import annotations

import ast
import itertools
import json
import os
import tempfile
from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jaxdmd import archive as arc
from jaxdmd import lines as ln
from jaxdmd import ties
from jaxdmd.fit import FitConfig, FitResult, Operator, fit_batch
from jaxdmd.prompts import Contract, Example, PromptRequest, Variable, parse_variable_requests
from jaxdmd.prompts import render as render_prompt
from jaxdmd.proposers import Sample
from jaxdmd.skeleton import Skeleton, SkeletonError, compile_skeleton
from jaxdmd.ties import settled


@dataclass(frozen=True)
class SearchConfig:
    """Hyper-parameters of a loop; the defaults are the paper's where it gives them."""

    n_islands: int = 10  # m
    prompts_per_round: int = 4
    samples_per_prompt: int = 4  # prompts_per_round * samples_per_prompt = n_b
    examples_per_prompt: int = 2
    tau_c: float = 0.2
    tau_l: float = 0.2
    epsilon: float = 0.01
    gamma: float = 0.01
    patience: int = 3  # R
    max_rounds: int = 15  # plus up to `patience` rounds for a variable that joined late
    top_k: int = 3  # skeletons whose variable requests are read at an extension
    reset_period: int = 4  # rounds between resets of the weaker half of the islands; 0: never
    recombine: bool = True
    fit: FitConfig = field(default_factory=FitConfig)


class Problem(eqx.Module):
    """The data a loop fits: every measured channel (the catalog) and the targets.

    ``variables`` holds all channels a skeleton could ever use (states and the whole catalog);
    a skeleton sees only those in its contract. ``targets`` are the state derivatives (DE loop)
    or the algebraic variables (AE loop), one row per target, several recordings concatenated.
    ``operator``, when given, is applied to every prediction before the comparison: for
    estimated derivatives, the smoothing matched to the estimator
    (:func:`jaxdmd.data.matched_filter`), so that the estimator's bias cancels.
    """

    variables: dict[str, jax.Array]
    targets: jax.Array
    target_names: tuple[str, ...] = eqx.field(static=True)
    catalog: tuple[Variable, ...] = eqx.field(static=True)
    weights: jax.Array | None = None
    operator: Operator | None = eqx.field(static=True, default=None)
    groups: jax.Array | None = None  # recording index of every sample (for cross-validation)

    def find(self, name: str) -> Variable | None:
        return next((v for v in self.catalog if v.name == name), None)


@dataclass(frozen=True)
class RoundReport:
    """What one ``step`` did, for progress display and the run's summary."""

    round: int
    n_samples: int  # the proposer's samples
    n_valid: int  # candidates fitted and registered: of the samples and the recombined one
    dropped: tuple[tuple[str, int], ...]  # reason -> count
    best_score: float
    improved: bool
    joined: tuple[str, ...] = ()  # variables that joined the library this round
    missing: tuple[str, ...] = ()  # requested variables the data lacks
    done: bool = False
    stop_reason: str = ""
    n_recombined: int = 0  # 1 when the recombination of the best lines was a candidate too


class SearchState(eqx.Module):
    """Everything a loop knows; an immutable pytree. Only ``key`` and the data are arrays."""

    contract: Contract = eqx.field(static=True)
    archive: arc.Archive = eqx.field(static=True)
    problem: Problem
    key: jax.Array
    config: SearchConfig = eqx.field(static=True)
    history: tuple[float, ...] = eqx.field(static=True, default=())
    # per round, each equation's best loss so far: an exact equation must not mask the others
    # (stopping and extension look at the worst of them, not at the best candidate's mean)
    equation_best: tuple[tuple[float, ...], ...] = eqx.field(static=True, default=())
    joined: tuple[tuple[str, int], ...] = eqx.field(static=True, default=())
    missing: tuple[str, ...] = eqx.field(static=True, default=())
    iteration: int = eqx.field(static=True, default=0)
    last_extension: int = eqx.field(static=True, default=0)
    done: bool = eqx.field(static=True, default=False)
    stop_reason: str = eqx.field(static=True, default="")
    # per round, why samples were dropped: (reason, count) pairs (the checker's rejections,
    # duplicates, fits that failed)
    dropped: tuple[tuple[tuple[str, int], ...], ...] = eqx.field(static=True, default=())


# ----------------------------------------------------------------------------------------------
# seeds, compilation, fitting


def linear_seed(contract: Contract) -> str:
    """The paper's seed skeleton: every target linear in every argument, plus a constant."""
    args = contract.arguments
    body, k = [], 0
    outputs = contract.outputs
    for out in outputs:
        terms = [f"p[{k}]"] + [f"p[{k + 1 + i}] * {a}" for i, a in enumerate(args)]
        k += 1 + len(args)
        body.append(f"    {out} = " + " + ".join(terms))
    head = f"def {contract.function_name}({', '.join([*args, 'p'])}):"
    return "\n".join([head, *body, f"    return {', '.join(outputs)}"]) + "\n"


def _compile(text: str, contract: Contract) -> Skeleton:
    try:
        return compile_skeleton(
            text,
            variables=contract.arguments,
            n_outputs=len(contract.targets),
            function_name=contract.function_name,
        )
    except SkeletonError:
        return compile_skeleton(text, variables=contract.arguments, n_outputs=len(contract.targets))


def fit_problem(
    skeletons: Sequence[Skeleton],
    problem: Problem,
    key: jax.Array,
    config: FitConfig | None = None,
) -> list[FitResult]:
    """Fit skeletons to a loop's problem (its variables, targets, weights and operator)."""
    config = config or FitConfig()
    names = sorted({a for s in skeletons for a in s.arguments})
    variables = {n: problem.variables[n] for n in names}
    return fit_batch(
        skeletons,
        variables,
        problem.targets,
        key=key,
        config=config,
        weights=problem.weights,
        operator=problem.operator,
    )


def _entry(skeleton: Skeleton, result: FitResult, round_: int) -> arc.Entry:
    return arc.Entry(
        source=skeleton.source,
        score=float(result.score),
        losses=tuple(float(x) for x in result.losses),
        params=tuple(float(x) for x in result.params),
        length=skeleton.length,
        round=round_,
        requests=tuple(skeleton.requests),
    )


def init(
    problem: Problem,
    contract: Contract,
    key: jax.Array,
    config: SearchConfig | None = None,
    seed: str | None = None,
) -> SearchState:
    """A fresh search: every island seeded with the linear skeleton (or ``seed``), fitted."""
    config = config or SearchConfig()
    _check_problem(problem, contract)
    key, fit_key = jax.random.split(key)
    skeleton = _compile(seed or linear_seed(contract), contract)
    (result,) = fit_problem([skeleton], problem, fit_key, config.fit)
    if result.error is not None:
        raise ValueError(f"the seed skeleton could not be fitted: {result.error}")
    archive = arc.new_archive(
        _entry(skeleton, result, 0),
        arc.ArchiveConfig(
            n_islands=config.n_islands,
            tau_c=config.tau_c,
            tau_l=config.tau_l,
            examples_per_prompt=config.examples_per_prompt,
            reset_period=config.reset_period,
        ),
    )
    return SearchState(
        contract=contract,
        archive=archive,
        problem=problem,
        key=key,
        config=config,
        history=(float(result.score),),
        equation_best=(tuple(float(x) for x in result.losses),),
        joined=tuple((v.name, 0) for v in contract.library),
    )


def _check_problem(problem: Problem, contract: Contract) -> None:
    missing = [n for n in contract.arguments if n not in problem.variables]
    if missing:
        raise ValueError(f"the data lack the contract's variables: {', '.join(missing)}")
    if problem.targets.shape[0] != len(contract.targets):
        raise ValueError(
            f"{len(contract.targets)} targets in the contract, "
            f"{problem.targets.shape[0]} rows of target data"
        )


# ----------------------------------------------------------------------------------------------
# the round


def prompts(state: SearchState) -> tuple[SearchState, tuple[PromptRequest, ...]]:
    """Draw in-context examples for this round's prompts and render them."""
    key, *keys = jax.random.split(state.key, state.config.prompts_per_round + 1)
    requests = []
    for k in keys:
        k_sample, k_seed = jax.random.split(k)
        island, entries = arc.sample_examples(state.archive, k_sample)
        examples = tuple(
            Example(source=e.source, score=e.score, losses=e.losses, params=e.params)
            for e in entries
        )
        seed = int(jax.random.randint(k_seed, (), 0, 2**31 - 1))
        requests.append(
            render_prompt(
                state.contract,
                examples,
                n_samples=state.config.samples_per_prompt,
                island=island,
                seed=seed,
            )
        )
    return replace_state(state, key=key), tuple(requests)


def step(state: SearchState, samples: Sequence[Sample]) -> tuple[SearchState, RoundReport]:
    """Evaluate one round of samples and apply the stopping and extension rules (pure)."""
    if state.done:
        raise ValueError(f"the search has ended ({state.stop_reason}); start a new one")
    round_ = state.iteration + 1
    key, fit_key, reset_key = jax.random.split(state.key, 3)
    dropped: Counter[str] = Counter()
    seen = {e.source for isl in state.archive.islands for e in isl.entries}
    candidates: list[tuple[Skeleton, int]] = []
    for sample in samples:
        try:
            skeleton = _compile(sample.text, state.contract)
        except SkeletonError as err:
            dropped[_reason(err)] += 1
            continue
        if skeleton.source in seen:
            dropped["already evaluated"] += 1
            continue
        seen.add(skeleton.source)
        candidates.append((skeleton, sample.island % state.config.n_islands))
    n_recombined = 0
    if state.config.recombine:
        recombined = _recombined(state)
        if recombined is not None and recombined[0].source not in seen:
            candidates.append(recombined)
            n_recombined = 1

    archive = state.archive
    best_before = arc.best(archive).score
    n_valid = 0
    if candidates:
        results = fit_problem([c[0] for c in candidates], state.problem, fit_key, state.config.fit)
        for (skeleton, island), result in zip(candidates, results, strict=True):
            if result.error is not None or not np.isfinite(result.score):
                dropped[f"fit: {result.error or 'non-finite score'}"] += 1
                continue
            n_valid += 1
            archive = arc.register(archive, _entry(skeleton, result, round_), island)
    period = state.config.reset_period
    if period and round_ % period == 0:
        archive = arc.reset_weak_islands(archive, reset_key)
    best = arc.best(archive).score
    state = replace_state(
        state,
        archive=archive,
        key=key,
        history=(*state.history, best),
        equation_best=(*state.equation_best, _equation_best(state, archive)),
        iteration=round_,
        dropped=(*state.dropped, tuple(sorted(dropped.items()))),
    )
    state, joined, missing = _maybe_extend(state)
    state = _maybe_stop(state)
    report = RoundReport(
        round=round_,
        n_samples=len(samples),
        n_valid=n_valid,
        dropped=tuple(sorted(dropped.items())),
        best_score=best,
        improved=best > best_before,
        joined=joined,
        missing=missing,
        done=state.done,
        stop_reason=state.stop_reason,
        n_recombined=n_recombined,
    )
    return state, report


def _reason(err: SkeletonError) -> str:
    text = getattr(err, "reason", None) or str(err)
    return text.split(":", 1)[0] if len(text) > 60 else text


def replace_state(state: SearchState, **changes: object) -> SearchState:
    """A copy of ``state`` with some fields replaced (the state itself never changes)."""
    names = [f for f in state.__dataclass_fields__]
    values = {n: getattr(state, n) for n in names}
    values.update(changes)
    return SearchState(**values)


def _recombined(state: SearchState) -> tuple[Skeleton, int] | None:
    """The best line of every equation, assembled into one candidate."""
    entries = [e for isl in state.archive.islands for e in isl.entries]
    if len(entries) < 2:
        return None
    n_out = len(state.contract.targets)
    chosen = [min(entries, key=lambda e, j=j: settled(e.losses[j])) for j in range(n_out)]
    if len({e.source for e in chosen}) < 2:
        return None
    try:
        lines = [ln.split_lines(e.source)[0][j] for j, e in enumerate(chosen)]
        source = ln.assemble(
            state.contract.function_name,
            state.contract.arguments,
            lines,
            state.contract.outputs,
        )
        skeleton = _compile(source, state.contract)
    except (ValueError, SkeletonError):
        return None
    # the lines' donors asked for these variables; the recombined candidate speaks for them
    unique = {json.dumps(r, sort_keys=True): r for e in chosen for r in e.requests}
    skeleton = replace(skeleton, requests=tuple(unique.values()))
    islands = [i for i, isl in enumerate(state.archive.islands) if chosen[0] in isl.entries]
    return skeleton, (islands[0] if islands else 0)


PROGRESS = 0.5  # an equation whose best loss halved in the last R rounds is still progressing
EXACT = 1e-12  # a loss below this is exact (the rest is rounding)


def _equation_best(state: SearchState, archive: arc.Archive) -> tuple[float, ...]:
    """Each equation's lowest loss so far (the archive's entries, and the rounds before)."""
    previous = state.equation_best[-1] if state.equation_best else ()
    rows = [e.losses for isl in archive.islands for e in isl.entries if len(e.losses)]
    if not rows:
        return tuple(previous)
    now = np.min(np.asarray(rows, dtype=float), axis=0)
    if len(previous) == len(now):
        now = np.minimum(now, previous)
    return tuple(float(x) for x in now)


def _equation_rows(state: SearchState) -> list[tuple[float, ...]]:
    """Per round, the equations' best losses (for a state written before they were kept: the
    best score's mean loss, as one)."""
    if len(state.equation_best) == len(state.history):
        return [row or (0.0,) for row in state.equation_best]
    return [(-h,) for h in state.history]


def _worst(state: SearchState) -> list[float]:
    """Per round, the largest of the equations' best losses."""
    return [max(row) for row in _equation_rows(state)]


def _progressing(state: SearchState) -> bool:
    """Whether some equation's best loss fell by more than a factor ``1 / PROGRESS`` over the
    last R rounds (losses below ``EXACT`` are exact: rounding is no progress)."""
    rows = _equation_rows(state)
    r = state.config.patience
    if len(rows) <= r:
        return True
    then, now = rows[-r - 1], rows[-1]
    return any(b < PROGRESS * a and a > EXACT for a, b in zip(then, now, strict=False))


def _gains(state: SearchState) -> list[float]:
    history = state.history[state.last_extension :]
    return [b - a for a, b in itertools.pairwise(history)]


def _maybe_extend(state: SearchState) -> tuple[SearchState, tuple[str, ...], tuple[str, ...]]:
    cfg = state.config
    gains = _gains(state)
    worst = _worst(state)[-1]
    if len(gains) < cfg.patience or max(gains[-cfg.patience :]) > cfg.epsilon or worst < cfg.gamma:
        return state, (), ()
    entries = (e for isl in state.archive.islands for e in isl.entries)
    top = sorted(entries, key=lambda e: -settled(e.score))
    requested: list[str] = []
    for entry in _distinct(top)[: cfg.top_k]:
        for name in parse_variable_requests(entry.requests):
            if name not in requested:
                requested.append(name)
    have = set(state.contract.arguments)
    joined, missing = [], []
    for name in requested:
        if name in have:
            continue
        variable = state.problem.find(name)
        if variable is not None and name in state.problem.variables:
            joined.append(variable)
        elif name not in state.missing:
            missing.append(name)
    contract = state.contract
    if joined:
        contract = replace(contract, library=(*contract.library, *joined))
    state = replace_state(
        state,
        contract=contract,
        joined=(*state.joined, *((v.name, state.iteration) for v in joined)),
        missing=(*state.missing, *missing),
        # a new variable restarts the stagnation window; without one, wait another R rounds
        last_extension=len(state.history) - 1,
    )
    return state, tuple(v.name for v in joined), tuple(missing)


def _distinct(entries: Sequence[arc.Entry]) -> list[arc.Entry]:
    seen, out = set(), []
    for e in entries:
        if e.source not in seen:
            seen.add(e.source)
            out.append(e)
    return out


def _maybe_stop(state: SearchState) -> SearchState:
    cfg = state.config
    recent = _worst(state)[-cfg.patience :]
    if (
        len(state.history) > cfg.patience
        and all(s < cfg.gamma for s in recent)
        and not _progressing(state)
    ):
        return replace_state(
            state,
            done=True,
            stop_reason=(
                f"every equation's loss below {cfg.gamma} for {cfg.patience} rounds, "
                "none still falling"
            ),
        )
    if state.iteration >= cfg.max_rounds:
        # a variable that joined in the last R rounds gets R rounds to be used: the round limit
        # must not bind right after the extension it was waiting for (at most R rounds more)
        last_join = max((r for _, r in state.joined), default=0)
        recent = last_join > 0 and state.iteration - last_join < cfg.patience
        if recent and state.iteration < cfg.max_rounds + cfg.patience:
            return state
        return replace_state(state, done=True, stop_reason=f"round limit ({cfg.max_rounds})")
    return state


# ----------------------------------------------------------------------------------------------
# the result


@dataclass(frozen=True)
class Equations:
    """A loop's result: the final skeleton, its fitted parameters and per-equation NMSE."""

    contract: Contract
    source: str
    params: tuple[float, ...]
    losses: tuple[float, ...]
    score: float

    def readable(self, *, by_name: bool = False) -> dict[str, str]:
        """Each target's equation with the fitted parameters written in: in the states, inputs
        and boundary (every output read by another inlined), or, with ``by_name``, as the
        skeleton writes it, an output that reads others reading them by their variables' names
        (a power written as a relation among the currents and voltages: ``P_e = 1.0 i_q v_q +
        ...``; as every line is where the skeleton has statements of other kinds)."""
        lhs = [f"d{t}/dt" if self.contract.loop == "DE" else t for t in self.contract.targets]
        own = ln.written_by_name(self.source) if by_name else None
        if own is not None:
            names = dict(zip(self.contract.outputs, self.contract.targets, strict=True))
            return {
                k: ln.substitute_params(ln.renamed(own[o], names), self.params)
                for k, o in zip(lhs, self.contract.outputs, strict=True)
            }
        lines, mappings = ln.split_lines(self.source)
        out = {}
        for key, line, mapping in zip(lhs, lines, mappings, strict=True):
            params = [self.params[i] for i in mapping]
            out[key] = ln.substitute_params(line.expr, params)
        return out

    def skeleton(self) -> Skeleton:
        return _compile(self.source, self.contract)


def _line_skeleton(contract: Contract, line: ln.Line) -> Skeleton:
    """The line compiled as a one-output skeleton, once per line text and arguments: the
    selection compiles the same lines again and again (its steps, folds and rounds)."""
    key = (line.text, tuple(contract.arguments))
    skeleton = _LINE_SKELETONS.get(key)
    if skeleton is None:
        source = ln.assemble("line", contract.arguments, [line], ["y"])
        skeleton = compile_skeleton(source, variables=contract.arguments, n_outputs=1)
        if len(_LINE_SKELETONS) >= 1 << 12:  # bounded: a long session compiles many lines
            _LINE_SKELETONS.clear()
        _LINE_SKELETONS[key] = skeleton
    return skeleton


_LINE_SKELETONS: dict[tuple[str, tuple[str, ...]], Skeleton] = {}


def compiled_lines(contract: Contract, lines: Sequence[ln.Line]) -> list[tuple[int, Skeleton]]:
    """Each line that compiles as a one-output skeleton, with its index in ``lines``."""
    out = []
    for i, line in enumerate(lines):
        try:
            out.append((i, _line_skeleton(contract, line)))
        except SkeletonError:
            continue
    return out


def sample_weights(problem: Problem, j: int) -> np.ndarray:
    """The sample weights of equation ``j`` (ones if the problem has none), ``[N]``."""
    n = problem.targets.shape[1]
    w = np.ones(n) if problem.weights is None else np.asarray(problem.weights, dtype=float)
    return np.broadcast_to(w, np.asarray(problem.targets).shape)[j] if w.ndim == 2 else w


def fold_fits(
    state: SearchState, j: int, skeletons: Sequence[Skeleton], groups: np.ndarray
) -> list[tuple[np.ndarray, list[FitResult]]]:
    """Equation ``j``'s one-output ``skeletons`` fitted once per group of ``groups``, that
    group's samples weighted out (with a single group: fitted on all samples). Returns, per
    fold, the held-out mask and the fit results."""
    problem = state.problem
    target = np.asarray(problem.targets[j])
    w = sample_weights(problem, j)
    names = sorted({a for sk in skeletons for a in sk.arguments})
    variables = {n: problem.variables[n] for n in names}
    folds = np.unique(groups)
    out = []
    for fold, g in enumerate(folds):
        held = groups == g
        results = fit_batch(
            skeletons,
            variables,
            target[None],
            key=jax.random.fold_in(state.key, 1000 + fold),
            config=state.config.fit,
            weights=(w * ~held)[None] if len(folds) > 1 else w[None],
            operator=problem.operator,
        )
        out.append((held, results))
    return out


def cross_validated_losses(state: SearchState, j: int, lines: Sequence[ln.Line]) -> np.ndarray:
    """Leave-one-recording-out NMSE of candidate lines for equation ``j``.

    Each line is refitted with one recording's samples weighted out (so a matched operator keeps
    its recordings intact) and scored on that recording; the held-out squared errors of all folds
    are summed (with the problem's sample weights) and normalised like the training NMSE. A line
    that fails scores ``inf``.
    """
    problem = state.problem
    target = np.asarray(problem.targets[j])
    var = float(np.var(target)) or 1.0
    w = sample_weights(problem, j)
    sse = np.full(len(lines), np.inf)
    compiled = compiled_lines(state.contract, lines)
    if not compiled:
        return sse
    for i, _ in compiled:
        sse[i] = 0.0
    skeletons = [sk for _, sk in compiled]
    names = sorted({a for sk in skeletons for a in sk.arguments})
    variables = {n: problem.variables[n] for n in names}
    for held, results in fold_fits(state, j, skeletons, np.asarray(problem.groups)):
        for (i, sk), result in zip(compiled, results, strict=True):
            if result.error is not None:
                sse[i] = np.inf
                continue
            pred = sk(variables, jnp.asarray(result.params))[0]
            if problem.operator is not None:
                pred = problem.operator(pred)
            sse[i] += float(np.sum(w[held] * (np.asarray(pred)[held] - target[held]) ** 2))
    return sse / (len(target) * var)


def final_equations(
    state: SearchState,
    tolerance: float = 0.05,
    floor: float = 1e-4,
    candidates: int = 15,
    prune: bool = True,
    include: Sequence[Equations] = (),
) -> Equations:
    """The result: for each equation, the simplest line that generalises as well as the best.

    With several recordings (``problem.groups``), the ``candidates`` archived lines of equation
    j with the lowest training NMSE are scored by leave-one-recording-out cross-validation
    (:func:`cross_validated_losses`); terms that only fit the noise of one recording do not carry
    over to another. Among the lines within ``tolerance`` (relative, plus ``floor``) of the best
    score, the one with the fewest parameters (then the fewest variables that are not states,
    since each must be closed by an algebraic equation, then the fewest nodes, then the lowest
    score) is kept. With ``prune`` (and cross-validation), summands are then taken out of the
    kept line one at a time (backward elimination: each round the summand whose removal leaves
    the lowest CV score goes, while that score stays within the same bound), because the archive
    holds the lines the search wrote, not every subset of them. With one recording the training
    NMSE is the score and nothing is pruned. The kept lines are assembled into one skeleton and
    refitted on all the data. The lines of ``include`` (other results, e.g. the choices of
    independent searches whose archives were pooled into ``state``) are candidates too.
    """
    entries = _distinct(e for isl in state.archive.islands for e in isl.entries)
    n_out = len(state.contract.targets)
    groups = state.problem.groups
    use_cv = groups is not None and len(np.unique(np.asarray(groups))) > 1
    states = {v.name for v in state.contract.states}
    chosen: list[ln.Line] = []
    for j in range(n_out):
        lines: dict[str, tuple[float, ln.Line]] = {}
        for e in sorted(entries, key=lambda e, j=j: settled(e.losses[j])):
            line = ln.split_lines(e.source)[0][j]
            if line.text not in lines:
                lines[line.text] = (e.losses[j], line)
            if len(lines) >= candidates:
                break
        for eq in include:  # e.g. each independent search's own choice, whatever its rank
            line = ln.split_lines(eq.source)[0][j]
            lines.setdefault(line.text, (eq.losses[j], line))
        options = list(lines.values())
        scores = (
            cross_validated_losses(state, j, [line for _, line in options])
            if use_cv
            else np.array([loss for loss, _ in options])
        )
        bound = float(np.min(scores)) * (1 + tolerance) + floor
        ranked = sorted(
            (
                line.n_params,
                len(line.variables() - states),  # each non-state needs closing (the AE loop)
                sum(1 for _ in ast.walk(line.expr)),
                settled(score),
                k,
            )
            for k, ((_, line), score) in enumerate(zip(options, scores, strict=True))
            if score <= bound
        )
        line = options[ranked[0][-1]][1]
        while prune and use_cv:
            variants = ln.without_each_summand(line)
            if not variants:
                break
            cv = cross_validated_losses(state, j, variants)
            best = ties.argmin(cv)
            if not cv[best] <= bound:
                break
            line = variants[best]
        chosen.append(line)
    source = ln.assemble(
        state.contract.function_name,
        state.contract.arguments,
        chosen,
        state.contract.outputs,
    )
    try:
        skeleton = _compile(source, state.contract)
        (result,) = fit_problem(
            [skeleton], state.problem, jax.random.fold_in(state.key, 7), state.config.fit
        )
    except SkeletonError as err:
        result = FitResult(np.zeros(0), np.zeros(0), -np.inf, str(err))
    if result.error is not None:  # fall back to the best archived candidate as it stands
        top = arc.best(state.archive)
        return Equations(state.contract, top.source, top.params, top.losses, top.score)
    return Equations(
        contract=state.contract,
        source=skeleton.source,
        params=tuple(float(x) for x in result.params),
        losses=tuple(float(x) for x in result.losses),
        score=float(result.score),
    )


# ----------------------------------------------------------------------------------------------
# persistence: the state is written atomically after each round


def _variable_dict(v: Variable) -> dict[str, str]:
    return {"name": v.name, "role": v.role, "unit": v.unit, "description": v.description}


def state_to_dict(state: SearchState) -> dict[str, object]:
    """Everything but the data (which the caller reloads), as JSON-ready values."""
    c = state.contract
    return {
        "contract": {
            "loop": c.loop,
            "targets": list(c.targets),
            "states": [_variable_dict(v) for v in c.states],
            "library": [_variable_dict(v) for v in c.library],
            "function_name": c.function_name,
            "system": c.system,
        },
        "archive": arc.to_dict(state.archive),
        "key": np.asarray(jax.random.key_data(state.key) if _is_typed(state.key) else state.key)
        .astype(np.uint32)
        .tolist(),
        "history": list(state.history),
        "equation_best": [list(row) for row in state.equation_best],
        "joined": [list(j) for j in state.joined],
        "missing": list(state.missing),
        "iteration": state.iteration,
        "last_extension": state.last_extension,
        "done": state.done,
        "stop_reason": state.stop_reason,
        "dropped": [[list(pair) for pair in row] for row in state.dropped],
    }


def _is_typed(key: jax.Array) -> bool:
    return jnp.issubdtype(key.dtype, jax.dtypes.prng_key)


def state_from_dict(
    data: Mapping[str, object], problem: Problem, config: SearchConfig
) -> SearchState:
    c = data["contract"]
    assert isinstance(c, dict)
    contract = Contract(
        loop=c["loop"],
        targets=tuple(c["targets"]),
        states=tuple(Variable(**v) for v in c["states"]),
        library=tuple(Variable(**v) for v in c["library"]),
        function_name=c["function_name"],
        system=c["system"],
    )
    return SearchState(
        contract=contract,
        archive=arc.from_dict(data["archive"]),
        problem=problem,
        key=jnp.asarray(np.asarray(data["key"], dtype=np.uint32)),
        config=config,
        history=tuple(float(x) for x in data["history"]),
        equation_best=tuple(
            tuple(float(x) for x in row)
            for row in data.get("equation_best", [])  # type: ignore[union-attr]
        ),
        joined=tuple((str(a), int(b)) for a, b in data["joined"]),
        missing=tuple(data["missing"]),
        iteration=int(data["iteration"]),
        last_extension=int(data["last_extension"]),
        done=bool(data["done"]),
        stop_reason=str(data["stop_reason"]),
        dropped=tuple(
            tuple((str(r), int(n)) for r, n in row)
            for row in data.get("dropped", [])  # type: ignore[union-attr]
        ),
    )


def write_json_atomic(path: str | os.PathLike[str], data: object) -> None:
    """Write JSON so that a reader sees the old file or the new one, never half of one."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w") as f:
            json.dump(data, f, indent=1, allow_nan=True)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
