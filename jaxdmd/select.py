"""The final model chosen by how it simulates recordings it was not fitted to.

The search ranks candidates by how they fit estimated derivatives; a user judges a model by how
it simulates. The two disagree where an equation fits the derivatives well but feeds back into
the others badly: a stand-in variable that is correlated with the true one on the training data,
a term that extrapolates beyond the training states, a slightly unstable mode. Here the
candidate lines of each equation (the archive's alternatives, ranked and pruned by
cross-validated derivative error in :func:`jaxdmd.search.final_equations`) are judged by
simulation instead:

1. **Each equation alone** (cheap): leave-one-recording-out, each line is fitted on the other
   recordings and the held-out recording is simulated with that equation's state integrated and
   every other channel played in (measured). Its error is the state's NRMSE (RMSE over the
   measured range). A line that does not vanish at the recorded operating point drifts, an
   unstable one diverges: both score badly without a special rule.
   The candidates are then varied term by term (:func:`_local_search`): the best lines lose
   one term or gain one of the equation's most frequent archived terms, and the variants are
   simulated in turn, so a stand-in the derivative fit preferred can be dropped and a weak
   term it could not see can be added even where no search wrote the true line.
2. **The equations together**: the best line of each equation (the simplest within
   ``tolerance`` of the best simulation error) and the derivative-chosen lines are combined;
   each combination is simulated coupled (all states integrated, the measured algebraic
   variables played in) on every recording, and the one that simulates best is kept, the
   simpler one on a tie.

3. **The algebraic equations** (:func:`select_algebraic`), after the AE loop: each algebraic
   variable the state equations use is chosen among its candidate lines (with lines built from
   products of the other algebraic variables' lines, as a power is built from voltages and
   currents: :func:`_composed_lines`) by simulating the held-out recording with that variable
   computed and the states it drives integrated; then the lines of each variable's Pareto
   front join the closed model one at a time, where they make it simulate better.
4. **The state equations again, closed** (:func:`select_states_closed`): each state equation's
   candidates (its line, the played-in front, the archive's best, and the local search with a
   swap move) simulated with every state integrated and every algebraic variable computed, the
   candidate fitted without the held-out recording; a line replaces the current one only on
   clear evidence (better by more than ``tolerance``), and only if it
   simulates no worse than ``tolerance`` allows with the algebraic variables played in.

Simulation runs on the host (NumPy, Heun's method on the recordings' sample grid, the lowered
programs of :mod:`jaxdmd.interp`): nothing is compiled, so a few hundred
candidate rollouts cost seconds. Play-in is linear between samples and never across an event (a
fault switched on or off), as :mod:`jaxdmd.rollout` plays signals in.

With one recording, held-out time blocks take the recordings' place (:func:`_held_out`): the
recording is cut into :data:`BLOCKS` contiguous blocks of equal duration (the SINDy baselines'
convention), each block's samples are weighted out of the fit in turn (the blocks are the
problem's groups, as the recordings are otherwise), and the held-out block is simulated from the
recording's states at its first sample (the estimated states, where the AE selection plays in
from them) with everything else played in as above; its NRMSE is taken over the block and
normalised by the whole recording's range per state (a settled block's own range is only its
noise). The coupled comparison of step 2 stays in-sample, as with several recordings. Each
report says what was held out (``held_out``: ``"recordings"`` or ``"time blocks (4)"``).
"""

from __future__ import annotations

import ast
import dataclasses
import functools
import itertools
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass

import equinox as eqx
import jax
import numpy as np

from jaxdmd import interp, reference, ties
from jaxdmd import lines as ln
from jaxdmd.data import Dataset, event_samples
from jaxdmd.proposers.offline import building_blocks, evaluate, subset_errors, wrap
from jaxdmd.search import (
    Equations,
    SearchState,
    _compile,
    compiled_lines,
    cross_validated_losses,
    fit_problem,
    fold_fits,
    replace_state,
    sample_weights,
)
from jaxdmd.skeleton import Skeleton, SkeletonError
from jaxdmd.ties import settled

__all__ = [
    "SelectionConfig",
    "reference_free",
    "score_host",
    "select_algebraic",
    "select_by_simulation",
    "select_states_closed",
    "simulate_host",
]


# terms of a line built from the other algebraic variables (:func:`_composed_lines`)
COMPOSED_TERMS = 4
# a held-out NMSE below this is round-off: the line is exact, and exact lines tie (which one
# fits to 1e-30 rather than 1e-31 depends on the machine's last bits, not on the data)
EXACT_NMSE = 1e-20


@dataclass(frozen=True)
class SelectionConfig:
    """How the final equations are chosen by simulation.

    Attributes:
        candidates: lines per equation simulated alone (the best by cross-validated derivative
            error, then their pruned variants).
        tolerance: relative simulation error within which a simpler line or model counts as
            as good as the best (complexity breaks ties). The rollouts are compared with noisy
            recordings and driven by noisy played-in channels: differences of a few percent
            are noise, not evidence.
        steps: at most this many rounds of the local search in term space after the first
            candidates: the best lines so far (the simplest within ``tolerance`` and the most
            accurate) are varied by dropping one term or adding one of the equation's ``terms``
            most frequent archived terms, and the variants are simulated in turn, until every
            best line has been varied (0: no local search).
        terms: how many of the archive's terms of an equation the local search may add.
        substeps: integration steps per sample interval (Heun's method: stable for modes
            faster than the samples by a factor of two, such as T''_q0 = 0.04 s at 100 Hz).
        blowup: a simulated state beyond ``blowup * (1 + max |measured|)`` has diverged.
    """

    candidates: int = 6
    tolerance: float = 0.25
    steps: int = 12
    terms: int = 12
    substeps: int = 1
    blowup: float = 1e3


# ----------------------------------------------------------------------------------------------
# host simulation


@dataclass(frozen=True)
class _Played:
    """Channels of one recording played in: values at sample k and at the right end of the
    interval (k, k+1] (the left value held over an interval that ends at an event)."""

    left: dict[str, np.ndarray]  # name -> [n - 1]
    right: dict[str, np.ndarray]  # name -> [n - 1]


def _played(ds: Dataset, names: Sequence[str]) -> _Played:
    t = np.asarray(ds.t, dtype=float)
    jump = event_samples(t, ds.events)[1:]  # interval k ends on an event sample
    left, right = {}, {}
    for n in names:
        x = np.asarray(ds[n], dtype=float)
        left[n] = x[:-1]
        right[n] = np.where(jump, x[:-1], x[1:])
    return _Played(left, right)


def _evaluate(program: interp.Program, args: list[np.ndarray], params: np.ndarray) -> np.ndarray:
    """Outputs ``[B, K]`` of a program at ``B`` points, each with its own parameter row."""
    return interp.pointwise_numpy(program, args, params)


def _distinct(recordings: Sequence[Dataset]) -> tuple[list[Dataset], np.ndarray]:
    """The distinct recordings among ``recordings`` (one given for several rows, as for
    candidates side by side, is read once) and each row's index among them ``[B]``."""
    where: dict[int, int] = {}  # id of a recording -> its index among the distinct ones
    distinct: list[Dataset] = []
    for ds in recordings:
        if id(ds) not in where:
            where[id(ds)] = len(distinct)
            distinct.append(ds)
    return distinct, np.asarray([where[id(ds)] for ds in recordings])


def _channels(recordings: Sequence[Dataset], channels: Sequence[str]) -> np.ndarray:
    """``[R, S, n]``: the ``channels`` of each recording."""
    return np.stack([[np.asarray(ds[c], dtype=float) for c in channels] for ds in recordings])


def _rollouts(
    program: interp.Program,
    targets: Sequence[str],
    params: np.ndarray,
    recordings: Sequence[Dataset],
    *,
    channels: Sequence[str] | None = None,
    algebraic: tuple[interp.Program, Sequence[str], np.ndarray] | None = None,
    substeps: int = 1,
    blowup: float = 1e3,
    windows: Sequence[tuple[int, int]] | None = None,
) -> Iterator[np.ndarray]:
    """The rollouts of :func:`simulate_host` a sample at a time: the simulated targets
    ``[B, S]`` at each sample of the time grid, in order (NaN from the first sample a rollout
    diverged at; all NaN after every one has). Holds no array as long as the rollouts."""
    targets = tuple(targets)
    first = recordings[0]
    ae_targets: tuple[str, ...] = () if algebraic is None else tuple(algebraic[1])
    needed = [*program.arguments, *(algebraic[0].arguments if algebraic else ())]
    played_names = sorted({a for a in needed if a not in targets and a not in ae_targets})
    t = np.asarray(first.t, dtype=float)
    for ds in recordings[1:]:
        if ds.n_samples != first.n_samples or not np.array_equal(np.asarray(ds.t), t):
            raise ValueError("simulate_host: the recordings must share their time grid")
    channels = targets if channels is None else tuple(channels)
    # a recording given for several rows is read and interpolated once; each row reads its
    # recording's values
    distinct, rows = _distinct(recordings)
    measured = _channels(distinct, channels)  # [R, S, n]
    played = [_played(ds, played_names) for ds in distinct]
    gather = None if len(distinct) == len(recordings) else rows
    bound = blowup * (1.0 + np.max(np.abs(measured), axis=2))[rows]  # [B, S]
    index = {s: i for i, s in enumerate(targets)}
    n = measured.shape[2]
    x = measured[rows, :, 0]
    yield x
    params = np.asarray(params, dtype=float)
    starts = None if windows is None else np.asarray([w[0] for w in windows])

    # the played-in values at each substep's ends, for every interval at once: [n - 1, R] per
    # name and weight (the same arithmetic as one interval at a time, without it at every stage)
    weights = [m / substeps for m in range(substeps + 1)]
    at: list[dict[str, np.ndarray]] = [{} for _ in weights]
    for a in played_names:
        x0 = np.stack([p.left[a] for p in played], axis=1)  # [n - 1, R]
        x1 = np.stack([p.right[a] for p in played], axis=1)
        for m, w in enumerate(weights):
            at[m][a] = (1 - w) * x0 + w * x1

    def field(x: np.ndarray, k: int, m: int) -> np.ndarray:
        values = {a: x[:, i] for a, i in index.items()}
        for a, v in at[m].items():
            values[a] = v[k] if gather is None else v[k][gather]
        if algebraic is not None:
            ae_program, _, ae_params = algebraic
            closed = _evaluate(ae_program, [values[a] for a in ae_program.arguments], ae_params)
            values.update({y: closed[:, i] for i, y in enumerate(ae_targets)})
        return _evaluate(program, [values[a] for a in program.arguments], params)

    with np.errstate(all="ignore"):
        for k in range(n - 1):
            h = (t[k + 1] - t[k]) / substeps
            for m in range(substeps):  # Heun's method (trapezoidal predictor-corrector)
                k1 = field(x, k, m)
                k2 = field(x + h * k1, k, m + 1)
                x = x + 0.5 * h * (k1 + k2)
            if starts is not None:  # a row whose block starts later holds the recording
                hold = k + 1 <= starts
                x[hold] = measured[rows[hold], :, k + 1]
            bad = ~(np.isfinite(x) & (np.abs(x) <= bound))  # each state on its own
            x[bad] = np.nan
            yield x
            if bad.all():
                for _ in range(k + 2, n):
                    yield x
                return


def simulate_host(
    program: interp.Program,
    targets: Sequence[str],
    params: np.ndarray,
    recordings: Sequence[Dataset],
    *,
    channels: Sequence[str] | None = None,
    algebraic: tuple[interp.Program, Sequence[str], np.ndarray] | None = None,
    substeps: int = 1,
    blowup: float = 1e3,
    windows: Sequence[tuple[int, int]] | None = None,
) -> np.ndarray:
    """Integrate ``d targets/dt = program(arguments, p)`` from each recording's first sample,
    every argument that is not a target played in from the recording. ``channels`` names the
    recorded channel of each target (default: the target's own name; several targets may be
    candidates for the same state, simulated side by side). ``algebraic`` closes the model: a
    program, its targets and its parameters ``[B, P]``, evaluated before the state equations at
    every stage on the simulated states and the played-in channels; its targets are then not
    played in (a DAE rollout).

    ``params`` is ``[B, P]``, one row per recording (``B == len(recordings)``; the recordings
    must share their time grid and events; one recording may be given for several rows, as
    for candidates simulated side by side, and is then interpolated once). ``windows`` (one
    ``(start, stop)`` sample range per row) starts row ``b``'s rollout at sample ``start`` from
    the recording's states there (a held-out time block, :func:`time_blocks`): before it the
    row holds the recorded states; only the samples in the window are meant to be scored
    (:func:`simulation_error`). Returns the simulated targets ``[B, S, n]`` (NaN from the first
    sample a rollout diverged at). Where only the error is wanted, :func:`score_host` gives it
    without holding the rollouts.
    """
    steps = _rollouts(
        program, targets, params, recordings, channels=channels, algebraic=algebraic,
        substeps=substeps, blowup=blowup, windows=windows,
    )  # fmt: skip
    x = next(steps)
    out = np.full((*x.shape, recordings[0].n_samples), np.nan)
    out[:, :, 0] = x
    for k, x in enumerate(steps, start=1):
        out[:, :, k] = x
    return out


#: the most squared errors :func:`score_host` holds at once (16 MB): the rollouts' errors are
#: summed along time this many values at a time, at most the whole recording's (then the sum
#: is NumPy's over the stored errors, the same to the bit as :func:`simulation_error`'s).
_SCORE_VALUES = 2**21


def score_host(
    program: interp.Program,
    targets: Sequence[str],
    params: np.ndarray,
    recordings: Sequence[Dataset],
    *,
    channels: Sequence[str] | None = None,
    against: Sequence[Dataset] | None = None,
    algebraic: tuple[interp.Program, Sequence[str], np.ndarray] | None = None,
    substeps: int = 1,
    blowup: float = 1e3,
    windows: Sequence[tuple[int, int]] | None = None,
) -> np.ndarray:
    """The NRMSE ``[B, S]`` of :func:`simulate_host`'s rollouts (the same arguments) against
    the recorded ``channels`` of ``against`` (one recording per row; default: ``recordings``,
    those played in), as :func:`simulation_error` scores them, without holding the rollouts:
    each row's squared errors are summed along time a chunk of samples at a time
    (:data:`_SCORE_VALUES`), so the memory does not grow with the length or the number of rows
    simulated side by side. inf where a rollout diverged."""
    channels = tuple(targets) if channels is None else tuple(channels)
    distinct, rows = _distinct(recordings if against is None else against)
    measured = _channels(distinct, channels)  # [R, S, n]
    b, s, n = len(rows), len(channels), measured.shape[2]
    if windows is None:
        lo, hi = np.zeros(b, dtype=int), np.full(b, n)
    else:
        lo, hi = (np.asarray([w[i] for w in windows]) for i in (0, 1))
    width = n if b * s * n <= _SCORE_VALUES else max(1, _SCORE_VALUES // (b * s))
    chunk = np.empty((b, s, width))
    total = np.zeros((b, s))
    steps = _rollouts(
        program, targets, params, recordings, channels=channels, algebraic=algebraic,
        substeps=substeps, blowup=blowup, windows=windows,
    )  # fmt: skip
    j = 0
    with np.errstate(all="ignore"):
        for k, x in enumerate(steps):
            squared = (x - measured[rows, :, k]) ** 2
            if windows is not None:  # a sample outside its row's window does not count
                squared = np.where(((k >= lo) & (k < hi))[:, None], squared, 0.0)
            chunk[:, :, j] = squared
            j += 1
            if j == width or k == n - 1:
                total += chunk[:, :, :j].sum(axis=-1)
                j = 0
        count = (np.minimum(hi, n) - np.maximum(lo, 0))[:, None]  # each row's window
        err = np.sqrt(total / count) / _range(measured, axis=-1)[rows]
    return np.where(np.isfinite(err), err, np.inf)


def _shared_grid(recordings: Sequence[Dataset]) -> bool:
    """Whether the recordings share one time grid (a batch of host rollouts needs it)."""
    t0 = np.asarray(recordings[0].t)
    return all(np.array_equal(np.asarray(r.t), t0) for r in recordings[1:])


def simulation_error(
    simulated: np.ndarray, recordings: Sequence[Dataset], targets,
    windows: Sequence[tuple[int, int]] | None = None,
) -> np.ndarray:  # fmt: skip
    """NRMSE ``[B, S]`` of simulated states against the recordings (RMSE over the measured
    range); inf where a rollout diverged. With ``windows`` (:func:`simulate_host`) the RMSE of
    row ``b`` is over its window, the range still the whole recording's."""
    measured = np.stack([[np.asarray(ds[s], dtype=float) for s in targets] for ds in recordings])
    return _nrmse(simulated, measured, windows)


def _range(measured: np.ndarray, axis: int = 2) -> np.ndarray:
    """The NRMSE's scale ``[B, S]`` of recordings ``[B, S, n]``: each state's measured range
    (its largest magnitude, at least 1, where it does not move)."""
    scale = np.ptp(measured, axis=axis)
    return np.where(scale > 0, scale, np.maximum(np.max(np.abs(measured), axis=axis), 1.0))


def _nrmse(
    simulated: np.ndarray, measured: np.ndarray,
    windows: Sequence[tuple[int, int]] | None = None,
) -> np.ndarray:  # fmt: skip
    """NRMSE ``[B, ...]`` of rollouts ``[B, ..., n]`` (time last), each series scaled by its
    measured range."""
    if windows is not None:
        return _windowed_nrmse(simulated, measured, windows)
    scale = _range(measured, axis=-1)
    err = np.sqrt(np.mean((simulated - measured) ** 2, axis=-1)) / scale
    return np.where(np.isfinite(err), err, np.inf)


def _windowed_nrmse(
    simulated: np.ndarray, measured: np.ndarray, windows: Sequence[tuple[int, int]]
) -> np.ndarray:
    """NRMSE ``[B, ...]`` of rollouts ``[B, ..., n]`` (time last) over each row's window
    ``(start, stop)``, scaled by the whole recording's range per state: a settled block's own
    range is only its noise."""
    mask = _window_mask(windows, simulated.shape[-1])
    mask = mask.reshape(mask.shape[0], *(1,) * (simulated.ndim - 2), mask.shape[1])
    squared = np.where(mask, (simulated - measured) ** 2, 0.0)
    err = np.sqrt(squared.sum(axis=-1) / mask.sum(axis=-1)) / _range(measured, axis=-1)
    return np.where(np.isfinite(err), err, np.inf)


def _window_mask(windows: Sequence[tuple[int, int]], n: int) -> np.ndarray:
    """``[B, n]``: True on the samples of each row's window."""
    k = np.arange(n)
    return np.stack([(k >= a) & (k < b) for a, b in windows])


# ----------------------------------------------------------------------------------------------
# folds: leave one recording (or one time block) out

BLOCKS = 4
"""Time blocks of equal duration a single training recording is cut into where a choice needs
held-out data (the convention of the SINDy baselines' thresholds, :mod:`jaxdmd.baselines`:
a quarter of the recording held out at a time)."""


def time_blocks(t: np.ndarray, k: int = BLOCKS) -> list[tuple[int, int]]:
    """The ``(start, stop)`` sample ranges of ``k`` contiguous blocks of equal duration of the
    time grid ``t`` (as :func:`jaxdmd.baselines._block_errors` cuts; empty blocks dropped)."""
    t = np.asarray(t, dtype=float)
    cuts = t[0] + (t[-1] - t[0]) * np.arange(1, k) / k
    edges = [0, *(int(i) for i in np.searchsorted(t, cuts)), t.size]
    return [(a, b) for a, b in itertools.pairwise(edges) if b > a]


@dataclass(frozen=True)
class _Holdout:
    """What a choice holds out: ``state``'s problem groups are the folds (recordings, or time
    blocks of one recording); ``recordings`` and ``played_from`` give one recording per fold
    (the single recording repeated for its blocks), ``windows`` each fold's block (None: the
    whole recording)."""

    state: SearchState
    recordings: list[Dataset]
    played_from: list[Dataset] | None
    windows: list[tuple[int, int]] | None
    label: str


def _held_out(
    state: SearchState, recordings: Sequence[Dataset],
    played_from: Sequence[Dataset] | None = None,
) -> _Holdout:  # fmt: skip
    """Folds of leave-one-out choices: the recordings, or with one recording its
    :data:`BLOCKS` time blocks (each block's samples weighted out of the fit in turn, then the
    block simulated from the recording's states at its first sample). Where the problem's
    samples are not the recording's (the integral form) one recording stays in-sample."""
    recordings = list(recordings)
    played = None if played_from is None else list(played_from)
    if len(recordings) > 1:
        return _Holdout(state, recordings, played, None, "recordings")
    n = recordings[0].n_samples
    blocks = time_blocks(np.asarray(recordings[0].t))
    if state.problem.targets.shape[1] != n or len(blocks) < 2:
        return _Holdout(state, recordings, played, None, "none (one recording, in-sample)")
    groups = np.zeros(n, dtype=int)
    for b, (start, stop) in enumerate(blocks):
        groups[start:stop] = b
    problem = eqx.tree_at(
        lambda p: p.groups, state.problem, jax.numpy.asarray(groups), is_leaf=lambda x: x is None
    )
    k = len(blocks)
    return _Holdout(
        replace_state(state, problem=problem), recordings * k,
        None if played is None else played * k, blocks, f"time blocks ({k})",
    )  # fmt: skip


def _folds(state: SearchState) -> np.ndarray:
    groups = np.asarray(state.problem.groups) if state.problem.groups is not None else None
    if groups is None:
        return np.zeros(state.problem.targets.shape[1], dtype=int)
    return groups


def _fold_params(state: SearchState, j: int, skeletons: Sequence[Skeleton]) -> np.ndarray:
    """Parameters of each line fitted with each recording left out: ``[lines, folds, P_max]``."""
    fits = fold_fits(state, j, skeletons, _folds(state))
    width = max(1, max(sk.n_params for sk in skeletons))
    out = np.full((len(skeletons), len(fits), width), np.nan)
    for f, (_, results) in enumerate(fits):
        for i, result in enumerate(results):
            if result.error is None:
                p = np.asarray(result.params, dtype=float)
                out[i, f, : p.size] = p
    return out


def used_variables(equations: Equations) -> set[str]:
    """The variables ``equations``' lines use (for state equations: the algebraic variables
    and inputs the states see)."""
    return set().union(*(line.variables() for line in ln.split_lines(equations.source)[0]))


def _complexity(line: ln.Line, states: set[str]) -> tuple[int, int, int]:
    return (
        line.n_params,
        len(line.variables() - states),
        sum(1 for _ in ast.walk(line.expr)),
    )


# ----------------------------------------------------------------------------------------------
# the selection


def _renamed(line: ln.Line, old: str, new: str) -> ln.Line:
    return ln.Line(ln.renamed(line.expr, {old: new}), line.n_params)


def _archive_lines(state: SearchState) -> list[tuple[tuple[float, ...], tuple[ln.Line, ...]]]:
    """Every distinct archived candidate's per-equation losses and lines, each line without
    the summands that move with the network's angle reference (:mod:`jaxdmd.reference`)."""
    from jaxdmd.search import _distinct

    entries = _distinct(e for isl in state.archive.islands for e in isl.entries)
    angles = reference.reference_angles(state.contract)
    out = [(e.losses, ln.split_lines(e.source)[0]) for e in entries]
    if not angles:
        return out
    data = reference.samples(state.problem.variables)
    verdicts: dict[str, bool] = {}
    return [
        (losses, tuple(
            reference.reference_free_line(line, angles, data, verdicts)[0] for line in lines
        ))
        for losses, lines in out
    ]  # fmt: skip


def reference_free(
    state: SearchState, equations: Equations
) -> tuple[Equations, dict[str, list[str]]]:
    """``equations`` (a loop's choice on ``state``'s problem) without the summands that move
    with the network's angle reference (:mod:`jaxdmd.reference`), refitted on the problem
    where any are left out; and per target the summands left out (empty: ``equations`` as
    they are)."""
    angles = reference.reference_angles(state.contract)
    if not angles:
        return equations, {}
    data = reference.samples(state.problem.variables)
    lines, dropped = [], {}
    for target, line in zip(
        state.contract.targets, ln.split_lines(equations.source)[0], strict=True
    ):
        free, moved = reference.reference_free_line(line, angles, data)
        lines.append(free)
        if moved:
            dropped[target] = moved
    if not dropped:
        return equations, {}
    refitted = _assemble(state, lines)
    if refitted is None:  # the fit failed (a line with summands left out is a valid skeleton)
        return equations, {}
    return refitted, dropped


def _candidate_lines(
    archived: Sequence[tuple[tuple[float, ...], tuple[ln.Line, ...]]], j: int, chosen: ln.Line,
    k: int,
) -> list[ln.Line]:  # fmt: skip
    """The chosen line, its pruned variants, and the ``k`` best distinct archived lines of
    equation ``j`` by training loss (the chosen line first)."""
    out: dict[str, ln.Line] = {chosen.text: chosen}
    for variant in ln.without_each_summand(chosen):
        out.setdefault(variant.text, variant)
    extra = 0
    for _, lines in sorted(archived, key=lambda e: settled(e[0][j])):
        if extra >= k:
            break
        if lines[j].text not in out:
            out[lines[j].text] = lines[j]
            extra += 1
    return list(out.values())


def _best_subset_lines(
    state: SearchState, j: int, features: Sequence[str], size: int, *, within: bool = False
) -> list[ln.Line]:
    """For each number of terms up to ``size`` (a constant counts as one), the subset of
    ``features`` (expressions, each written as it follows ``p[n] *``) and the constant with
    the least leave-one-recording-out error of algebraic variable ``j`` on the loop's
    regressors (one fold where the problem has one group), as a line with one parameter per
    term. A feature that is not finite or is constant on the data is left out; with
    ``within``, also one that is constant within every fold."""
    problem = state.problem
    data = {k: np.asarray(v, dtype=float) for k, v in problem.variables.items()}
    target = np.asarray(problem.targets[j], dtype=float)
    groups = _folds(state)
    folds = [groups == g for g in np.unique(groups)]
    kept: list[str] = []
    columns: list[np.ndarray] = []
    for text in features:
        try:
            with np.errstate(all="ignore"):
                expr = ast.parse(text, mode="eval").body
                column = np.broadcast_to(evaluate(expr, data), target.shape).astype(float)
        except (KeyError, ValueError, TypeError, ZeroDivisionError):
            continue
        varies = any(np.std(column[f]) > 0 for f in folds) if within else np.std(column) > 0
        if np.all(np.isfinite(column)) and varies:
            kept.append(text)
            columns.append(column)
    if not kept:
        return []
    root = np.sqrt(sample_weights(problem, j))
    x = np.stack([np.ones_like(target), *columns], axis=1) * root[:, None]
    y = target * root
    out: list[ln.Line] = []
    # the constant (column 0) counts as a term
    for subsets, sse in subset_errors(x, y, folds, min(size, x.shape[1])):
        best = [int(i) for i in subsets[ties.argmin(sse)]]
        terms = [f"p[{n}]" if i == 0 else f"p[{n}] * {kept[i - 1]}" for n, i in enumerate(best)]
        expr = ast.parse(" + ".join(terms), mode="eval").body
        out.append(ln.renumbered(ln.Line(ast.fix_missing_locations(expr), len(terms))))
    return out


def _composed_lines(
    state: SearchState, j: int, fit_choice: Equations, size: int = COMPOSED_TERMS
) -> list[ln.Line]:
    """Candidate lines of algebraic variable ``j`` built from products of the others.

    Algebraic variables are often products of one another: a machine's electrical power is
    ``v_d i_d + v_q i_q`` (plus its armature losses ``r_a (i_d^2 + i_q^2)``) and its reactive
    power ``v_q i_d - v_d i_q``, where the voltages are projections of the terminal phasor and
    the currents linear in the states. Written in the states alone, such a line is a sum of
    products that the search has to assemble term by term and rarely does; written in the other
    variables, it is two products. Here the pairwise products of the other variables' lines in
    ``fit_choice`` (their fitted parameters written in as constants, so that each stands for its
    variable as the model computes it) are the features of :func:`_best_subset_lines`: lines in
    the states, inputs and boundary only, so the closed model needs nothing measured. Only
    products: a sum of other lines is already a line in the states, and a single other line as
    a feature would be a stand-in that hides its terms. Nothing here knows what any variable
    is. The lines are candidates; simulation chooses (:func:`select_algebraic`)."""
    others = [k for k in range(len(ln.split_lines(fit_choice.source)[0])) if k != j]
    return composed_lines(state, j, fit_choice, others, size)


def composed_lines(
    state: SearchState, j: int, equations: Equations, factors: Sequence[int],
    size: int = COMPOSED_TERMS,
) -> list[ln.Line]:  # fmt: skip
    """The best subsets (:func:`_best_subset_lines`) of the pairwise products of
    ``equations``' lines ``factors`` (their fitted parameters written in as constants) as lines
    of algebraic variable ``j`` (see :func:`_composed_lines`); none where the problem has an
    operator."""
    if state.problem.operator is not None:
        return []
    lines, mappings = ln.split_lines(equations.source)
    values = np.asarray(equations.params, dtype=float)
    others = [_with_constants(lines[k], values[list(mappings[k])]) for k in factors]
    products = [
        f"({ast.unparse(ast.BinOp(left=a, op=ast.Mult(), right=b))})"
        for a, b in itertools.combinations_with_replacement(others, 2)
    ]
    return _best_subset_lines(state, j, products, size)


# one term of a composed line: its parameter's index in the equations, and the two lines it
# multiplies (None: the constant)
_Term = tuple[int, tuple[int, int] | None]


def _composed_terms(equations: Equations) -> dict[int, list[_Term]]:
    """The lines of ``equations`` built from products of its other lines
    (:func:`composed_lines`), recognised by their factors: each factor is, to the last digit,
    another line of ``equations`` with its parameters written in, and that line is not itself
    composed. Per composed line, its terms in order."""
    lines, mappings = ln.split_lines(equations.source)
    values = np.asarray(equations.params, dtype=float)
    written = {
        ast.unparse(_with_constants(line, values[list(m)])): k
        for k, (line, m) in enumerate(zip(lines, mappings, strict=True))
    }
    found: dict[int, list[_Term]] = {}
    for j, line in enumerate(lines):
        terms: list[_Term] = []
        for summand in ln.summands(line.expr):
            if (i := ln.param_index(summand)) is not None:
                terms.append((mappings[j][i], None))
                continue
            product = summand.right if isinstance(summand, ast.BinOp) else None
            i = ln.param_index(summand.left) if isinstance(summand, ast.BinOp) else None
            if (
                i is None or not isinstance(summand.op, ast.Mult)  # type: ignore[union-attr]
                or not (isinstance(product, ast.BinOp) and isinstance(product.op, ast.Mult))
            ):  # fmt: skip
                break
            a = written.get(ast.unparse(product.left))
            b = written.get(ast.unparse(product.right))
            if a is None or b is None or j in (a, b):
                break
            terms.append((mappings[j][i], (a, b)))
        else:
            if any(factors is not None for _, factors in terms):
                found[j] = terms
    return {
        j: terms for j, terms in found.items()
        if not any(k in found for _, factors in terms if factors for k in factors)
    }  # fmt: skip


def written_as_relations(
    equations: Equations, relations: dict[int, list[tuple[float, tuple[int, int] | None]]]
) -> tuple[Skeleton, list[float]] | None:
    """``equations`` with each line ``j`` of ``relations`` written as a relation among the
    other lines' outputs, read by name after them (``P_e_ = p[12] * i_q_ * v_q_ + ...``): its
    terms, each a coefficient (a parameter, set to the value given) times the product of two
    other lines' outputs (their indices), or alone (None). Returns the compiled skeleton and its
    parameters (the other lines' as they are, then the relations' coefficients); None where it
    does not compile (over a skeleton's budget)."""
    lines, mappings = ln.split_lines(equations.source)
    contract = equations.contract
    outputs = list(contract.outputs)
    kept = [k for k in range(len(lines)) if k not in relations]
    params = [float(equations.params[i]) for k in kept for i in mappings[k]]
    statements: list[str] = []
    for j, terms in relations.items():
        parts = []
        for value, factors in terms:
            parts.append(
                f"p[{len(params)}]" if factors is None
                else f"p[{len(params)}] * {outputs[factors[0]]} * {outputs[factors[1]]}"
            )  # fmt: skip
            params.append(float(value))
        statements.append(f"{outputs[j]} = {' + '.join(parts)}")
    source = ln.assemble(
        contract.function_name, contract.arguments, [lines[k] for k in kept],
        [outputs[k] for k in kept], after=statements, returns=outputs,
    )  # fmt: skip
    try:
        return _compile(source, contract), params
    except SkeletonError:
        return None


@dataclass(frozen=True)
class Linked:
    """Equations with their composed lines written as relations (:func:`linked`), and the way
    back to the form the rest of the pipeline reads."""

    equations: Equations  # the relations' form
    given: Equations  # the form with every line in the states
    origin: tuple[int, ...]  # each parameter's index in ``given``
    terms: dict[int, list[_Term]]  # ``given``'s composed lines (:func:`_composed_terms`)

    def given_params(self, params: Sequence[float]) -> np.ndarray:
        """Parameters of the relations' form as ``given``'s (the composed lines' factors are
        not parameters there: :meth:`back` writes them in)."""
        values = np.asarray(self.given.params, dtype=float).copy()
        values[list(self.origin)] = np.asarray(params, dtype=float)
        return values

    def back(self, fitted: Equations) -> Equations | None:
        """``given`` with the parameters of ``fitted`` (the relations' form, refitted): the other
        lines take theirs, and each composed line is built again from those lines as they now
        are (their parameters written in), its coefficients ``fitted``'s. The same outputs, in
        the form the rest of the pipeline reads (every line in the states alone). None where
        the line so written exceeds a skeleton's size limits (its constants written out
        longer)."""
        lines, mappings = ln.split_lines(self.given.source)
        values = self.given_params(fitted.params)
        written = [
            _with_constants(line, values[list(m)]) for line, m in zip(lines, mappings, strict=True)
        ]
        new = list(lines)
        params: list[float] = []
        for j, mapping in enumerate(mappings):
            if j not in self.terms:
                params += [float(values[i]) for i in mapping]
                continue
            parts = []
            for n, (index, factors) in enumerate(self.terms[j]):
                params.append(float(values[index]))
                if factors is None:
                    parts.append(f"p[{n}]")
                else:
                    product = ast.BinOp(written[factors[0]], ast.Mult(), written[factors[1]])
                    parts.append(f"p[{n}] * ({ast.unparse(product)})")
            new[j] = ln.Line(ast.parse(" + ".join(parts), mode="eval").body, len(parts))
        contract = self.given.contract
        source = ln.assemble(contract.function_name, contract.arguments, new, contract.outputs)
        try:
            skeleton = _compile(source, contract)
        except SkeletonError:
            return None
        return dataclasses.replace(self.given, source=skeleton.source, params=tuple(params))


def linked(equations: Equations) -> Linked | None:
    """``equations`` with each line built from products of its other lines
    (:func:`composed_lines`, those lines' parameters written in as constants) written as the
    relation it is among them (:func:`written_as_relations`: the products read the other lines'
    outputs by name, as :func:`jaxdmd.identities.with_identities` writes a measured relation).
    The outputs are the same; what differs is a fit of the parameters: the composed line then
    moves with the lines it is built from (and its variable's data inform their parameters)
    instead of keeping copies of them as they were (:meth:`Linked.back` writes a fit back).
    None where no line is composed or the relations do not compile."""
    terms = _composed_terms(equations)
    if not terms:
        return None
    values = equations.params
    written = written_as_relations(
        equations, {j: [(values[i], factors) for i, factors in t] for j, t in terms.items()}
    )
    if written is None:
        return None
    skeleton, params = written
    _, mappings = ln.split_lines(equations.source)
    origin = [i for k, m in enumerate(mappings) if k not in terms for i in m]
    origin += [i for t in terms.values() for i, _ in t]
    relations = dataclasses.replace(equations, source=skeleton.source, params=tuple(params))
    return Linked(relations, equations, tuple(origin), terms)


def _block_lines(state: SearchState, j: int, size: int = COMPOSED_TERMS) -> list[ln.Line]:
    """Candidate lines of algebraic variable ``j`` from the best subsets of the level-one
    building blocks (each variable or its deviation from 1, sines and cosines of angle
    differences, the boundary phasor's projections: :func:`jaxdmd.proposers.offline.
    building_blocks`), by held-out fit (:func:`_best_subset_lines`).

    The AE loop scores a candidate by all its equations at once, so a line that fits one
    variable better on held-out data but the training data a little worse than the loop's
    many-term line rarely enters the archive: a stator current with x'_d small is linear in
    two or four blocks (``e''_d`` and ``V sin(delta - theta)``, and the armature resistance's
    ``e'_q`` and ``V cos(delta - theta)``), while the archive may hold only a linear fit in
    every state. The exhaustive subset search over the blocks writes such lines directly, as
    the offline proposer's subset edit does during the search, up to ``size`` terms. A block
    that does not vary within any recording (an input held constant in each) is left out: on
    held-out recordings it fits the recordings' offsets, and a line built from it is a
    stand-in for whatever differs between them."""
    if state.problem.operator is not None:
        return []
    contract = state.contract
    data = {k: np.asarray(v, dtype=float) for k, v in state.problem.variables.items()}
    blocks, angles = building_blocks([*contract.states, *contract.library], data)
    names = [wrap(name) for name in dict.fromkeys([*angles, *blocks])]
    moving = reference.reference_angles(contract)
    if moving:  # a block that moves with the angle reference is no block of a line
        probes = reference.samples(data)
        names = [
            n for n in names
            if not reference.moves_with_reference(ast.parse(n, mode="eval").body, moving, probes)
        ]  # fmt: skip
    return _best_subset_lines(state, j, names, size, within=True)


def _frequent_terms(lines: Sequence[ln.Line], k: int, by_text: bool = False) -> list[ln.Line]:
    """The ``k`` one-parameter terms found in most of ``lines``; ties in the order the lines
    come, or by the terms' text (``by_text``)."""
    count: dict[str, int] = {}
    first: dict[str, ln.Line] = {}
    for line in lines:
        for term in ln.simple_summands(line):
            count[term.text] = count.get(term.text, 0) + 1
            first.setdefault(term.text, term)
    order = (lambda key: (-count[key], key)) if by_text else (lambda key: -count[key])
    return [first[key] for key in sorted(first, key=order)[:k]]  # stable: input order on ties


def _term_pool(
    archived: Sequence[tuple[tuple[float, ...], tuple[ln.Line, ...]]], j: int, k: int
) -> list[ln.Line]:
    """The ``k`` one-parameter terms of equation ``j`` found in most archived lines (ties: in
    the order of the lines' training loss)."""
    ranked = sorted(archived, key=lambda e: settled(e[0][j]))
    return _frequent_terms([lines[j] for _, lines in ranked], k)


def _shared_terms(
    archived: Sequence[tuple[tuple[float, ...], tuple[ln.Line, ...]]], k: int
) -> list[ln.Line]:
    """The ``k`` one-parameter terms found in most archived lines of any equation."""
    return _frequent_terms([line for _, lines in archived for line in lines], k, by_text=True)


def _key(line: ln.Line) -> frozenset[str]:
    return frozenset(_terms(line))


def _neighbours(
    line: ln.Line, pool: Sequence[ln.Line], states: set[str] | None = None
) -> list[ln.Line]:
    """``line`` with one term dropped, or with one of ``pool``'s terms added; with ``states``,
    also with a term that reads a variable other than a state swapped for one of ``pool``'s (a
    stand-in and the term it stands in for are nearly collinear on the training data, so that
    neither adding the one nor dropping the other alone simulates better: the swap is one
    move)."""
    have = _terms(line)
    added = [ln.with_summand(line, t) for t in pool if not (_terms(t) & have)]
    dropped = ln.without_each_summand(line)
    swapped = []
    for rest in dropped if states is not None else ():
        if not any(_names(term) - states for term in have - _terms(rest)):
            continue
        swapped += [ln.with_summand(rest, t) for t in pool if not (_terms(t) & have)]
    return [*dropped, *added, *swapped]


def _names(term: str) -> set[str]:
    """The variables a term (its text, :func:`_terms`) reads."""
    tree = ast.parse(term, mode="eval")
    return {n.id for n in ast.walk(tree) if isinstance(n, ast.Name)} - {"p", "jnp", "np"}


def _local_search(
    lines: list[ln.Line], errors: np.ndarray, pool: Sequence[ln.Line],
    score: Callable[[list[ln.Line]], np.ndarray], config: SelectionConfig, states: set[str],
    swap: bool = False,
) -> tuple[list[ln.Line], np.ndarray]:  # fmt: skip
    """Vary the best lines term by term and ``score`` the variants, until the best lines have
    all been varied (at most ``config.steps`` rounds); with ``swap`` a term in a variable other
    than a state is also swapped for each of ``pool``'s (:func:`_neighbours`).

    The lines varied in each round are the two simplest within ``tolerance`` of the best
    simulation error and the best itself, each once: a line that enters the beam in the last
    round is varied in the next (its own one-term-shorter variant may be the answer). A
    stand-in term that the derivative fit preferred is dropped here, and a small term it could
    not see (a slow or weak effect) is added, as long as the held-out simulation says so."""
    seen = {_key(line) for line in lines}
    varied: set[frozenset[str]] = set()
    for _ in range(config.steps):
        finite = np.isfinite(errors)
        if not finite.any():
            break
        best = float(np.min(errors))
        ranked = sorted(
            (_complexity(line, states), settled(e), i)
            for i, (line, e) in enumerate(zip(lines, errors, strict=True))
            if e <= best * (1 + config.tolerance)
        )
        best_lines = [*(i for *_, i in ranked[:2]), ties.argmin(errors)]
        beam = dict.fromkeys(i for i in best_lines if _key(lines[i]) not in varied)
        if not beam:
            break
        varied.update(_key(lines[i]) for i in beam)
        new: list[ln.Line] = []
        for i in beam:
            for variant in _neighbours(lines[i], pool, states if swap else None):
                key = _key(variant)
                if key not in seen:
                    seen.add(key)
                    new.append(variant)
        if not new:
            break
        lines = [*lines, *new]
        errors = np.concatenate([errors, score(new)])
    return lines, errors


def _choose(
    lines: Sequence[ln.Line], errors: np.ndarray, config: SelectionConfig, states: set[str]
) -> tuple[ln.Line, dict[str, object]]:
    """The simplest line within ``tolerance`` of the best simulation error, and its report:
    the most accurate dozen candidates, how many were simulated, the Pareto front. Of equally
    simple lines the first (the loop's own line: every caller lists it first) is chosen, then
    the one that simulates best: within the tolerance the simulation cannot tell them apart,
    and the loop's cross-validated fit chose the first (on Table I's generator 31 seed 2, the
    PSAT line of d e'_q/dt with i_d and the stand-in with v_q for it, 0.01006 and 0.00983)."""
    bound = float(np.min(errors)) * (1 + config.tolerance)
    ranked = sorted(
        (_complexity(line, states), i != 0, settled(err), i)
        for i, (line, err) in enumerate(zip(lines, errors, strict=True))
        if err <= bound
    )
    line = lines[ranked[0][-1]]
    return line, {
        "candidates": [
            {"line": lines[i].text, "simulation_nrmse": float(errors[i])}
            for i in np.argsort(errors, kind="stable")[:12]
        ],
        "simulated": len(lines),
        "pareto": _pareto(
            [
                (len(ln.summands(ln_.expr)), float(e), ln_.text)
                for ln_, e in zip(lines, errors, strict=True)
                if np.isfinite(e)
            ]
        ),
        "chosen": line.text,
    }


def _usable_fits(
    state: SearchState, j: int, lines: Sequence[ln.Line]
) -> tuple[list[tuple[int, Skeleton]], np.ndarray, list[tuple[int, int]]]:
    """The lines that compile as equation ``j`` (``(index, skeleton)``), their parameters
    fitted with each recording left out (``[compiled, folds, P_max]``, :func:`_fold_params`),
    and the ``(compiled index, line index)`` of those whose every fold fit is finite."""
    compiled = compiled_lines(state.contract, lines)
    if not compiled:
        return compiled, np.zeros((0, 1, 1)), []
    params = _fold_params(state, j, [sk for _, sk in compiled])
    usable = [
        (c, i) for c, (i, sk) in enumerate(compiled)
        if np.all(np.isfinite(params[c, :, : sk.n_params]))
    ]  # fmt: skip
    return compiled, params, usable


def _per_recording(rows: np.ndarray, state: SearchState, n: int) -> np.ndarray:
    """Fold parameter rows ``[folds, P]`` as one row per recording (``n``): the fold that left
    each recording (or time block, :class:`_Holdout`) out, or the single fit repeated when there
    is nothing to hold out."""
    single = len(np.unique(_folds(state))) == 1
    return np.repeat(rows, n, axis=0) if single or rows.shape[0] == 1 else rows


def _single_errors(
    state: SearchState, j: int, lines: Sequence[ln.Line], recordings: Sequence[Dataset],
    config: SelectionConfig, windows: Sequence[tuple[int, int]] | None = None,
) -> np.ndarray:  # fmt: skip
    """Each line's simulation error, its equation's state integrated alone, left-out fits
    (one recording per fold; ``windows``: each fold's held-out time block, :class:`_Holdout`).

    The lines are simulated side by side: those that are sums of one-parameter terms as rows
    of one batch (:func:`_side_by_side`), any other in one program whose output i is line i
    with the state renamed to its own copy, so one evaluation per step serves every
    candidate."""
    target = state.contract.targets[j]
    errors = np.full(len(lines), np.inf)
    lines = [ln.renumbered(line) for line in lines]
    compiled, params, usable = _usable_fits(state, j, lines)
    if not usable:
        return errors
    union, members, wide, alone = _side_by_side(usable, lines, params, state, len(recordings))
    if members:
        source = ln.assemble("batch", [target, *state.contract.arguments], [union], ["y0"])
        program = _batch_program(source, 1)
        if program is None:
            alone = usable
        else:
            err = _batch_errors(program, (target,), wide, recordings, recordings, config, windows)
            for i, e in zip(members, err, strict=True):
                errors[i] = float(e)

    def simulate(group: list[tuple[int, int]]) -> None:
        """Simulate a group of lines in one program; halve the group if it is too large."""
        copies = [f"{target}_c{i}" for _, i in group]
        renamed = [
            _renamed(lines[i], target, name) for (_, i), name in zip(group, copies, strict=True)
        ]
        used = set().union(*(line.variables() for line in renamed))
        played = [a for a in state.contract.arguments if a in used and a != target]
        source = ln.assemble("batch", [*played, *copies], renamed, [f"y{i}" for _, i in group])
        program = _batch_program(source, len(group))
        if program is None:
            if len(group) > 1:
                simulate(group[: len(group) // 2])
                simulate(group[len(group) // 2 :])
            return
        rows = np.concatenate(
            [params[c, :, : max(compiled[c][1].n_params, lines[i].n_params)] for c, i in group],
            axis=1,
        )  # [folds, sum of the lines' parameters], in the assembled order
        rows = _per_recording(rows, state, len(recordings))
        err = score_host(
            program, copies, rows, recordings, channels=[target] * len(copies),
            substeps=config.substeps, blowup=config.blowup, windows=windows,
        )  # [B, lines]  # fmt: skip
        for (_, i), e in zip(group, err.mean(axis=0), strict=True):
            errors[i] = float(e)

    if alone:
        simulate(alone)
    return errors


def _batch_program(source: str, n_outputs: int) -> interp.Program | None:
    """The program of a batch of lines side by side; None where it cannot be written (the
    caller simulates the lines in smaller groups or alone)."""
    try:
        return interp.lower(source, n_outputs=n_outputs)
    except (interp.LoweringError, ValueError):
        return None


def _batch_errors(
    program: interp.Program, states: Sequence[str], rows: np.ndarray,
    recordings: Sequence[Dataset], against: Sequence[Dataset], config: SelectionConfig,
    windows: Sequence[tuple[int, int]] | None = None,
    algebraic: tuple[interp.Program, Sequence[str], np.ndarray] | None = None,
) -> np.ndarray:  # fmt: skip
    """The mean NRMSE of each of ``k`` candidates run side by side: parameter rows
    ``[k * B, P]`` (candidate after candidate, one row per recording) simulated on the ``B``
    ``recordings`` (and ``windows``, one per recording) and scored against the states of
    ``against`` (one per recording); ``algebraic``'s parameters, if one row per row of ``rows``,
    go with them. Returns ``[k]``."""
    k = rows.shape[0] // len(recordings)
    err = score_host(
        program, states, rows, list(recordings) * k, against=list(against) * k,
        algebraic=algebraic, substeps=config.substeps, blowup=config.blowup,
        windows=None if windows is None else list(windows) * k,
    )  # [k * B, S]  # fmt: skip
    return err.reshape(k, -1).mean(axis=1)


def _side_by_side(
    usable: Sequence[tuple[int, int]], lines: Sequence[ln.Line], params: np.ndarray,
    state: SearchState, n: int,
) -> tuple[ln.Line, list[int], np.ndarray, list[tuple[int, int]]]:  # fmt: skip
    """The usable lines (``(compiled index, line index)`` of :func:`_usable_fits`, ``lines``
    renumbered) as rows of one batch: the line holding every one-parameter term of those that
    are sums of distinct one-parameter terms (:func:`_union`), the indices of those lines, their
    parameters ``[lines * n, U]`` (line after line, one row per recording, zero on the terms a
    line lacks: the union then computes each line's value), and the other usable lines
    (simulated on their own)."""
    union, maps = _union([lines[i] for _, i in usable])
    members: list[int] = []
    blocks: list[np.ndarray] = []
    alone: list[tuple[int, int]] = []
    for (c, i), where in zip(usable, maps, strict=True):
        if where is None:
            alone.append((c, i))
            continue
        rows = _per_recording(params[c, :, : lines[i].n_params], state, n)
        wide = np.zeros((rows.shape[0], max(1, union.n_params)))
        wide[:, where] = rows
        members.append(i)
        blocks.append(wide)
    return union, members, np.concatenate(blocks) if blocks else np.zeros((0, 1)), alone


def _coupled_error(
    equations: Equations, recordings: Sequence[Dataset], config: SelectionConfig
) -> float:
    """Mean NRMSE of all states simulated together (measured algebraic variables played in),
    the parameters as given (fitted on all recordings)."""
    skeleton = equations.skeleton()
    program = interp.program_of(skeleton)
    if program is None:
        return float("inf")
    targets = tuple(equations.contract.targets)
    p = np.asarray(equations.params, dtype=float)[None, : max(1, skeleton.n_params)]
    rows = np.repeat(p, len(recordings), axis=0)
    err = score_host(
        program, targets, rows, recordings, substeps=config.substeps, blowup=config.blowup
    )
    return float(np.mean(err))


def _skeleton(state: SearchState, chosen: Sequence[ln.Line]) -> Skeleton | None:
    """The loop's function written with the ``chosen`` lines, or None where it is not a valid
    skeleton (lines composed from others carry their coefficients: several in one model can
    outgrow the size limits)."""
    contract = state.contract
    source = ln.assemble(contract.function_name, contract.arguments, chosen, contract.outputs)
    try:
        return _compile(source, contract)
    except SkeletonError:
        return None


def _assemble(state: SearchState, chosen: Sequence[ln.Line]) -> Equations | None:
    skeleton = _skeleton(state, chosen)
    if skeleton is None:
        return None
    (result,) = fit_problem([skeleton], state.problem, jax.random.fold_in(state.key, 7))
    if result.error is not None:
        return None
    return Equations(
        contract=state.contract,
        source=skeleton.source,
        params=tuple(float(x) for x in result.params),
        losses=tuple(float(x) for x in result.losses),
        score=float(result.score),
    )


def _pareto(points: Sequence[tuple[int, float, str]]) -> list[dict[str, object]]:
    front, best = [], np.inf
    for terms, err, text in sorted(points, key=lambda p: (p[0], p[1])):
        if err < best:
            front.append({"terms": terms, "simulation_nrmse": err, "line": text})
            best = err
    return front


def select_by_simulation(
    state: SearchState,
    derivative_choice: Equations,
    recordings: Sequence[Dataset],
    config: SelectionConfig | None = None,
) -> tuple[Equations, dict[str, object]]:
    """The DE loop's final equations chosen by simulation (see the module's docstring).

    ``derivative_choice`` is :func:`jaxdmd.search.final_equations`'s result (the lines chosen
    by cross-validated derivative error); ``recordings`` the training recordings the loop's
    problem was built from (same order). Returns the chosen equations (parameters fitted on all
    recordings, as the search fits) and a report: what was held out (``held_out``: the
    recordings, or with one recording its time blocks), per equation the simulation error of
    each candidate line, the Pareto front (terms against simulation error), the chosen line;
    and the coupled simulation error of the derivative choice and of the chosen model.
    """
    config = config or SelectionConfig()
    contract = state.contract
    states = {v.name for v in contract.states}
    recordings = list(recordings)
    sims = recordings
    if not _shared_grid(recordings):
        return derivative_choice, {"skipped": "the recordings do not share a time grid"}
    derived, _ = ln.split_lines(derivative_choice.source)
    archived = _archive_lines(state)
    picked: list[ln.Line] = []
    held = _held_out(state, recordings)
    report: dict[str, object] = {"held_out": held.label, "equations": {}}
    for j, target in enumerate(contract.targets):
        lines = _candidate_lines(archived, j, derived[j], config.candidates)

        def score(new: list[ln.Line], j: int = j) -> np.ndarray:
            return _single_errors(held.state, j, new, held.recordings, config, held.windows)

        errors = score(lines)
        lines, errors = _local_search(
            lines, errors, _term_pool(archived, j, config.terms), score, config, states
        )
        if not np.isfinite(np.min(errors)):
            picked.append(derived[j])
            report["equations"][target] = {"kept": "no candidate simulates"}  # type: ignore[index]
            continue
        line, report["equations"][target] = _choose(lines, errors, config, states)  # type: ignore[index]
        picked.append(line)
    by_derivatives = _coupled_error(derivative_choice, sims, config)
    report["coupled_nrmse_derivative_choice"] = by_derivatives
    if [p.text for p in picked] == [d.text for d in derived]:
        report["coupled_nrmse"] = by_derivatives
        report["changed"] = []
        return derivative_choice, report
    chosen = _assemble(state, picked)
    by_simulation = _coupled_error(chosen, sims, config) if chosen is not None else np.inf
    report["coupled_nrmse_simulation_choice"] = by_simulation
    if chosen is None or not by_simulation <= by_derivatives * (1 + config.tolerance):
        report["coupled_nrmse"] = by_derivatives
        report["changed"] = []
        report["kept"] = "the derivative choice simulates better coupled"
        return derivative_choice, report
    report["coupled_nrmse"] = by_simulation
    report["changed"] = [
        t for t, a, b in zip(contract.targets, picked, derived, strict=True) if a.text != b.text
    ]
    return dataclasses.replace(chosen), report


# ----------------------------------------------------------------------------------------------
# the closed model (DAE): the algebraic variables computed, never played in


def dae_errors(
    de: Equations,
    ae_program: interp.Program,
    ae_targets: Sequence[str],
    ae_params: np.ndarray,
    recordings: Sequence[Dataset],
    config: SelectionConfig,
    played_from: Sequence[Dataset] | None = None,
    windows: Sequence[tuple[int, int]] | None = None,
) -> np.ndarray:
    """NRMSE ``[B, S]`` of the states of the closed model (the algebraic variables computed by
    the AE program) simulated on each of ``recordings``; inf where a rollout diverged (all inf
    if the state equations do not lower). ``ae_params`` is one parameter vector, or ``[B, P]``:
    one row per recording (a recording may be given for several rows, as for options side by
    side). The other channels and the initial states are played in from ``played_from``
    (default: ``recordings``). ``windows``: each row's time block (:func:`simulate_host`)."""
    targets = tuple(de.contract.targets)
    skeleton = de.skeleton()
    program = interp.program_of(skeleton)
    if program is None:
        return np.full((len(recordings), len(targets)), np.inf)
    b = len(recordings)
    p = np.asarray(de.params, dtype=float)[None, : max(1, skeleton.n_params)]
    q = np.asarray(ae_params, dtype=float)
    if q.ndim == 1:
        q = np.repeat(q[None, : max(1, ae_program.n_params)], b, axis=0)
    return score_host(
        program, targets, np.repeat(p, b, axis=0),
        list(recordings) if played_from is None else list(played_from),
        against=recordings, algebraic=(ae_program, tuple(ae_targets), q),
        substeps=config.substeps, blowup=config.blowup, windows=windows,
    )  # fmt: skip


def simulation_nrmse(
    de: Equations,
    recordings: Sequence[Dataset],
    ae: Equations | None = None,
    config: SelectionConfig | None = None,
) -> float:
    """Mean NRMSE of the states simulated on ``recordings``: the state equations with the
    measured algebraic variables played in, or closed by ``ae`` (a DAE rollout); inf if a
    rollout diverged or the recordings do not share a time grid. The yardstick of every choice
    :func:`jaxdmd.pipeline.discover` makes after the search (a refit is kept only if the model
    simulates the training recordings as well as before)."""
    config = config or SelectionConfig()
    recordings = list(recordings)
    if not _shared_grid(recordings):
        return float("inf")
    if ae is None:
        return _coupled_error(de, recordings, config)
    skeleton = ae.skeleton()
    program = interp.program_of(skeleton)
    if program is None:
        return float("inf")
    errors = dae_errors(de, program, ae.contract.targets, np.asarray(ae.params), recordings, config)
    return float(np.mean(errors))


def _with_constants(line: ln.Line, params: Sequence[float]) -> ast.expr:
    """``line``'s expression with its fitted parameters written in as constants (exact)."""

    class _Sub(ast.NodeTransformer):
        def visit_Subscript(self, node: ast.Subscript) -> ast.expr:
            if isinstance(node.value, ast.Name) and node.value.id == "p":
                value = float(params[node.slice.value])  # type: ignore[attr-defined]
                const = ast.Constant(abs(value))
                return ast.UnaryOp(ast.USub(), const) if value < 0 else const
            return self.generic_visit(node)

    return ast.fix_missing_locations(_Sub().visit(ln.copy_tree(line.expr)))


def _closed_errors(
    ae_state: SearchState, j: int, lines: Sequence[ln.Line], de: Equations,
    recordings: Sequence[Dataset], config: SelectionConfig,
    played_from: Sequence[Dataset] | None = None,
    windows: Sequence[tuple[int, int]] | None = None,
) -> np.ndarray:  # fmt: skip
    """Each algebraic line's simulation error with only its own variable closed.

    Leave-one-recording-out: the line is fitted (on the AE loop's regressors) with each
    recording left out, and the held-out recording is simulated with every state integrated by
    the state equations ``de`` (their parameters as fitted), the line's variable computed by the
    line from the simulated states, and every other channel played in. The error is the mean
    NRMSE of the states. The candidates are simulated side by side: those that are sums of
    one-parameter terms as rows of one batch (:func:`_side_by_side`), the batch's line closing
    the state equations at every stage; any other in one program whose outputs are the state
    equations once per candidate, the line written in where its variable stands and the states
    renamed to the candidate's own copies."""
    target = ae_state.contract.targets[j]
    states = tuple(de.contract.targets)
    de_lines, mappings = ln.split_lines(de.source)
    de_params = np.asarray(de.params, dtype=float)
    fixed = [
        _with_constants(line, de_params[list(m)])
        for line, m in zip(de_lines, mappings, strict=True)
    ]
    errors = np.full(len(lines), np.inf)
    lines = [ln.renumbered(line) for line in lines]
    _, params, usable = _usable_fits(ae_state, j, lines)
    if not usable:
        return errors
    # the states the variable drives are integrated, the others played in
    driven = [
        (s, expr) for s, expr in zip(states, fixed, strict=True)
        if any(isinstance(x, ast.Name) and x.id == target for x in ast.walk(expr))
    ]  # fmt: skip
    if not driven:
        return errors
    states = tuple(s for s, _ in driven)
    source_of_play = list(recordings) if played_from is None else list(played_from)
    arguments = [*dict.fromkeys([*de.contract.arguments, *ae_state.contract.arguments])]
    b = len(recordings)
    union, members, wide, alone = _side_by_side(usable, lines, params, ae_state, b)
    if members:
        # the lines as the closure of the driven state equations (their parameters written in)
        de_lines = [ln.Line(expr, 0) for _, expr in driven]
        outputs = [f"y{k}" for k in range(len(states))]
        try:
            ae_program = interp.lower(
                ln.assemble("algebraic", ae_state.contract.arguments, [union], ["y0"]),
                n_outputs=1,
            )
            program = interp.lower(
                ln.assemble("closed", [*states, *arguments], de_lines, outputs),
                n_outputs=len(outputs),
            )
        except (interp.LoweringError, ValueError):
            alone = usable
        else:
            err = _batch_errors(
                program, states, np.zeros((len(members) * b, 1)), source_of_play, recordings,
                config, windows, algebraic=(ae_program, (target,), wide),
            )  # fmt: skip
            for i, e in zip(members, err, strict=True):
                errors[i] = float(e)

    def simulate(group: list[tuple[int, int]]) -> None:
        names: list[str] = []
        closed: list[ln.Line] = []
        blocks: list[np.ndarray] = []
        for c, i in group:
            n = lines[i].n_params
            for s, expr in driven:  # each uses the variable: the line's parameters
                line = ln.Line(ln.inlined(expr, {target: lines[i].expr}), n)
                for other, _ in driven:
                    line = _renamed(line, other, f"{other}_c{i}")
                closed.append(line)
                names.append(f"{s}_c{i}")
                blocks.append(params[c, :, :n])
        used = set().union(*(line.variables() for line in closed))
        played = [a for a in arguments if a in used and a not in names]
        outputs = [f"y{k}" for k in range(len(names))]
        source = ln.assemble("closed", [*played, *names], closed, outputs)
        program = _batch_program(source, len(names))
        if program is None:
            if len(group) > 1:
                simulate(group[: len(group) // 2])
                simulate(group[len(group) // 2 :])
            return
        rows = _per_recording(np.concatenate(blocks, axis=1), ae_state, len(recordings))
        err = score_host(
            program, names, rows, source_of_play, channels=[*states] * len(group),
            against=recordings, substeps=config.substeps, blowup=config.blowup, windows=windows,
        ).reshape(len(recordings), len(group), len(states))  # fmt: skip
        for (_, i), e in zip(group, err.mean(axis=(0, 2)), strict=True):
            errors[i] = float(e)

    if alone:
        simulate(alone)
    return errors


def _front(lines: Sequence[ln.Line], errors: np.ndarray, states: set[str]) -> list[ln.Line]:
    """The Pareto front of candidate lines: by complexity, each line that simulates better
    than every simpler one."""
    front, best = [], np.inf
    ranked = sorted(
        (_complexity(line, states), settled(e), i)
        for i, (line, e) in enumerate(zip(lines, errors, strict=True))
        if np.isfinite(e)
    )
    for _, e, i in ranked:
        if e < best:
            front.append(lines[i])
            best = e
    return front


def _fits(state: SearchState, j: int, new: ln.Line, old: ln.Line, config: SelectionConfig) -> bool:
    """Whether ``new`` fits algebraic variable ``j`` (held out as the selection holds out:
    recordings or time blocks) within ``tolerance`` of ``old``. A closed simulation is slow to
    see a small term of an algebraic line (an armature resistance in a stator current); the
    variable's own held-out fit is not."""
    losses = cross_validated_losses(state, j, [ln.renumbered(new), ln.renumbered(old)])
    return bool(losses[0] <= max(losses[1] * (1 + config.tolerance), EXACT_NMSE))


# The log-likelihood of each of several algebraic equation sets (their parameters fitted by
# it, less BIC's penalty): :func:`select_algebraic`'s arbiter where the closed model and the
# held-out fit cannot tell a simpler line from the one the step would take or keep
# (:func:`_likelier`). :func:`jaxdmd.pipeline.discover`
# passes the likelihood with the states unknown (:func:`jaxdmd.refine.joint_likelihood`).
Likelihood = Callable[[Sequence[Equations]], Sequence[float]]
# the simpler lines per variable that the likelihood may be asked about, each with the equations
# it would replace (each costs a joint refit; on Table I no second line asked about was ever taken)
LIKELIHOOD_TRIALS = 1


def _by_held_out_fit(
    ae_state: SearchState, held: SearchState, derived: list[ln.Line], fit_choice: Equations,
    used: set[str], config: SelectionConfig, states: set[str], report: dict[str, object],
) -> tuple[list[ln.Line], Equations, list[str]]:  # fmt: skip
    """The lines of the algebraic variables the state equations do not use, chosen by how they
    fit their variable on held-out data (recordings or time blocks: ``held``'s folds) among the
    fit choice and the building blocks' best subsets (:func:`_block_lines`): the simplest
    within ``tolerance`` of the best. Such a variable does not drive a state, so no simulation
    tells its lines apart; but the lines built from it (:func:`_composed_lines`: a power from a
    voltage and a current) carry its errors into the closed model. Returns the lines (the
    others as derived), the equations the composed lines are built from (``fit_choice`` where
    nothing changed, else all lines fitted on every recording) and the variables changed; each
    one's candidates and choice go to ``report["equations"]``."""
    lines = list(derived)
    changed: list[str] = []
    for j, target in enumerate(ae_state.contract.targets):
        if target in used:
            continue
        known = {derived[j].text}
        options = [derived[j], *(c for c in _block_lines(held, j) if c.text not in known)]
        losses = cross_validated_losses(held, j, [ln.renumbered(c) for c in options])
        if not np.isfinite(np.min(losses)):
            continue
        bound = max(float(np.min(losses)) * (1 + config.tolerance), EXACT_NMSE)
        eligible = [i for i, loss in enumerate(losses) if loss <= bound]
        best = min(eligible, key=lambda i: (_complexity(options[i], states), settled(losses[i])))
        report["equations"][target] = {  # type: ignore[index]
            "by": "held-out fit (the state equations do not use it)",
            "candidates": [
                {"line": c.text, "held_out_nmse": float(loss)}
                for c, loss in zip(options, losses, strict=True)
            ],
            "chosen": options[best].text,
        }
        if best != 0:
            lines[j] = options[best]
            changed.append(target)
    if not changed:
        return lines, fit_choice, []
    basis = _assemble(ae_state, lines)
    if basis is None:
        return list(derived), fit_choice, []
    return lines, basis, changed


def select_algebraic(
    ae_state: SearchState,
    fit_choice: Equations,
    de: Equations,
    recordings: Sequence[Dataset],
    config: SelectionConfig | None = None,
    played_from: Sequence[Dataset] | None = None,
    likelihood: Likelihood | None = None,
) -> tuple[Equations, dict[str, object]]:
    """The AE loop's final equations chosen by how the model simulates, as the state equations
    are (:func:`select_by_simulation`).

    The AE loop ranks its candidates by how they fit the algebraic variables on *estimated*
    states. An algebraic equation of a machine amplifies its regressors' errors (a stator
    current by 1/x'_d): the true line fits those estimates no better than a stand-in that is
    measured cleanly or bends to their errors (an input, products and squares of states), and
    the stand-in fails when the model is simulated. So each algebraic variable the state
    equations use is chosen here by simulation:

    1. **Each variable alone**: its candidate lines (the fit choice, its pruned variants, the
       archive's best, the lines built from the other algebraic variables
       (:func:`_composed_lines`), then the local search in term space, whose pool adds the
       loop's most frequent terms over all its equations) are fitted with each recording left
       out, and the held-out recording is simulated with that variable computed by the line
       and the states it drives integrated, every other channel played in
       (:func:`_closed_errors`). The simplest line within ``tolerance`` of the best is that
       variable's choice.
    2. **Closed**: one variable at a time, in the loop's order, the choice and every line of
       the variable's Pareto front (the simplest line for each simulation error reached in
       step 1) replace its current line (at first the fit choice) in the closed model (every
       state integrated, every algebraic variable computed, fits held out:
       :func:`_closed_loro`), and the training recordings are simulated. A line may replace
       the current one if the closed model then simulates better by more than ``tolerance``,
       or if it is simpler, simulates no worse and fits its variable on held-out data within
       ``tolerance`` of the current line (:func:`_fits`); of those within ``tolerance`` of
       the best closed error, the simplest does. A line no larger (in parameters) within
       ``tolerance`` on both yardsticks but not taken so is what the noise cannot decide: a
       stand-in term that offsets another equation's error helps the closed model a little,
       and so does, for the other side, a small term the line needs (an armature resistance);
       stand-ins that bend to the estimated states' errors fit the variable about as well as
       the true terms, and simulate about as well. There ``likelihood`` decides
       (:func:`_likelier`; none given: the current line stays).
       (Step 1 alone can prefer a line with stand-in terms that helps while the other
       variables are played in; the closed model tells them apart.) Where another variable's
       line has changed by then, the lines built from the others' lines
       (:func:`_composed_lines`) are built again from the lines the closed model now has and
       join the options; so does, for a variable the states use, the current line with each of
       its terms dropped (a stand-in the derivative fit kept: on Table I's generator 31 seed
       2, i_q's e'_q P_m), and after each change the new line's, until no shorter line is
       taken (:func:`_closed_choice`). A line the whole model cannot be written with (the size
       limits: lines composed from others carry their coefficients) is not an option.

    A variable the state equations do not use is not simulated: its line is the simplest within
    ``tolerance`` of the best held-out fit among its fit choice and the building blocks' best
    subsets (:func:`_by_held_out_fit`), chosen first, since the lines built from it carry its
    errors into the closed model.

    ``recordings`` are the training recordings (the measured states the rollouts are compared
    with), in the order of the AE problem's groups; ``played_from`` the recordings the other
    channels and the initial states are played in from (default: the same;
    :func:`jaxdmd.pipeline.discover` passes the AE loop's regressors, the estimated states).
    With one recording, its time blocks are held out instead (:func:`_held_out`).
    Returns the equations (parameters fitted on all recordings) and a report: what was held
    out (``held_out``), per variable the candidates, the Pareto front, the choice and the
    closed error with it, and the likelihood's verdicts (``likelihood``: each line asked about
    and its gain in nats over the equations it would replace); the closed error of the fit
    choice and of the result; the variables changed.
    """
    config = config or SelectionConfig()
    recordings = list(recordings)
    if not _shared_grid(recordings):
        return fit_choice, {"skipped": "the recordings do not share a time grid"}
    contract = ae_state.contract
    states = {v.name for v in de.contract.states}
    used = used_variables(de)
    derived, _ = ln.split_lines(fit_choice.source)
    archived = _archive_lines(ae_state)
    # the algebraic variables share their physics (a stator current and the power are built
    # from the same voltages): the loop's most frequent terms over all its equations may
    # serve any of them
    shared = _shared_terms(archived, 2 * config.terms)
    picked: list[ln.Line] = []
    fronts: dict[int, list[ln.Line]] = {}
    held = _held_out(ae_state, recordings, played_from)
    report: dict[str, object] = {"held_out": held.label, "equations": {}}
    derived, basis, by_fit_changed = _by_held_out_fit(
        ae_state, held.state, derived, fit_choice, used, config, states, report
    )
    for j, target in enumerate(contract.targets):
        if target not in used:
            picked.append(derived[j])
            continue
        lines = _candidate_lines(archived, j, derived[j], config.candidates)
        known = {line.text for line in lines}
        for c in [*_block_lines(held.state, j), *_composed_lines(held.state, j, basis)]:
            if c.text not in known:
                known.add(c.text)
                lines.append(c)

        def score(new: list[ln.Line], j: int = j) -> np.ndarray:
            return _closed_errors(
                held.state, j, new, de, held.recordings, config, held.played_from, held.windows
            )

        errors = score(lines)
        pool = _term_pool(archived, j, config.terms)
        lines, errors = _local_search(lines, errors, [*pool, *shared], score, config, states)
        if not np.isfinite(np.min(errors)):
            picked.append(derived[j])
            report["equations"][target] = {"kept": "no candidate simulates"}  # type: ignore[index]
            continue
        line, report["equations"][target] = _choose(lines, errors, config, states)  # type: ignore[index]
        picked.append(line)
        fronts[j] = _front(lines, errors, states)
    # the variables' choices join the closed model one at a time: each line of the variable's
    # front (and its choice) replaces the current line in turn, and the closed model simulates
    # the training recordings (fits held out) with it
    fits: dict[tuple[int, str], np.ndarray | None] = {}
    by_fit, by_fit_held_out = _closed_loro(
        held.state, derived, de, held.recordings, config, held.played_from, fits, held.windows
    )
    report["dae_nrmse_fit_choice"] = by_fit
    report["dae_nrmse_fit_choice_per_held_out"] = [float(x) for x in by_fit_held_out]
    current_lines, error = list(derived), by_fit
    changed = list(by_fit_changed)
    assembled: dict[tuple[str, ...], Equations | None] = {}
    likelihoods: dict[tuple[str, ...], float] = {}
    for j, target in enumerate(contract.targets):
        options = {line.text: line for line in (picked[j], *fronts.get(j, ()))}
        if target in used and any(
            current_lines[k].text != derived[k].text for k in range(len(derived)) if k != j
        ):
            # the lines built from the others as the closed model now has them (fitted once
            # per set of lines: consecutive variables often see the same)
            key = tuple(line.text for line in current_lines)
            if key not in assembled:
                assembled[key] = _assemble(ae_state, current_lines)
            now = assembled[key]
            for line in _composed_lines(held.state, j, now) if now is not None else ():
                options.setdefault(line.text, line)
        entry = report["equations"][target]  # type: ignore[index]
        moved, before = False, error
        # then, for a variable the states use, the current line with each of its terms dropped
        # (a stand-in the derivative fit kept), again after each change, until no shorter line
        # is taken (another variable's closed trials cannot tell its lines apart: its own
        # held-out fit chose among its subsets)
        while True:
            for line in ln.without_each_summand(current_lines[j]) if target in used else ():
                options.setdefault(line.text, line)
            taken = _closed_choice(
                held, ae_state, j, options, current_lines, error, de, config, fits, states,
                likelihood, likelihoods, entry,
            )  # fmt: skip
            if taken is None:
                break
            current_lines, error = taken
            moved, options = True, {}
        if "closed" in entry:  # the closed error with the variable's own choice
            entry["dae_nrmse"] = next(
                (c["dae_nrmse"] for c in entry["closed"] if c["line"] == picked[j].text), before
            )
        if moved:
            changed.append(target)
    report["dae_nrmse"] = error
    report["changed"] = changed
    chosen = _assemble(ae_state, current_lines) if changed else None
    if chosen is None:
        report["changed"] = []
        return fit_choice, report
    return chosen, report


def _closed_choice(
    held: _Holdout, ae_state: SearchState, j: int, options: dict[str, ln.Line],
    current_lines: list[ln.Line], error: float, de: Equations, config: SelectionConfig,
    fits: dict[tuple[int, str], np.ndarray | None], states: set[str],
    likelihood: Likelihood | None, likelihoods: dict[tuple[str, ...], float],
    entry: dict[str, object],
) -> tuple[list[ln.Line], float] | None:  # fmt: skip
    """One step of :func:`select_algebraic`'s closed choice for variable ``j``: ``options``
    (line texts to lines) each in place of the current line, simulated closed; the simplest of
    those that simulate better by more than the tolerance, or no worse and simpler while they
    fit the variable within the tolerance (or a simpler one that ``likelihood`` rates above
    the lines it would replace: :func:`_likelier`): the lines and their error, or None. The
    trials go into ``entry["closed"]``."""
    now = current_lines[j]
    options = {
        text: line for text, line in options.items()
        if text != now.text
        # no line the whole model cannot be written with (lines composed from others carry
        # their coefficients: several in one model can outgrow the size limits, and a choice
        # that cannot be written is lost with all the others)
        and _skeleton(ae_state, [*current_lines[:j], line, *current_lines[j + 1 :]]) is not None
    }  # fmt: skip
    if not options:
        return None
    candidates = list(options.values())
    trial_errors, held_out = _closed_trials(
        held.state, current_lines, j, candidates, de, held.recordings, config,
        held.played_from, fits, held.windows,
    )  # fmt: skip
    trials = [
        (line, [*current_lines[:j], line, *current_lines[j + 1 :]], e)
        for line, e in zip(candidates, trial_errors, strict=True)
    ]
    closed = entry.setdefault("closed", [])
    closed += [  # type: ignore[operator]
        {"line": line.text, "dae_nrmse": e, "per_held_out": [float(x) for x in rows]}
        for (line, _, e), rows in zip(trials, held_out, strict=True)
    ]
    best = min([error, *(e for *_, e in trials)])
    near = [t for t in trials if t[2] <= best * (1 + config.tolerance)]
    # the lines simpler than the current one that simulate no worse
    simpler = {
        t[0].text for t in near
        if t[2] <= error and _complexity(t[0], states) < _complexity(now, states)
    }  # fmt: skip
    # whether a line fits the variable within tolerance, where that is asked: a simpler line
    # that simulates no worse, and with a likelihood any line no larger than the current one
    fitting = {
        t[0].text: _fits(held.state, j, t[0], now, config)
        for t in near
        if t[0].n_params <= now.n_params and (likelihood is not None or t[0].text in simpler)
    }
    eligible = [
        t for t in near if t[2] <= error and (
            t[2] * (1 + config.tolerance) < error
            or (t[0].text in simpler and fitting[t[0].text])
        )
    ]  # fmt: skip
    taken = min(eligible, key=lambda t: (_complexity(t[0], states), settled(t[2])), default=None)
    if likelihood is not None:  # within the noise on both yardsticks, and not taken
        undecided = [t for t in near if t not in eligible and fitting.get(t[0].text, False)]
        likelier = _likelier(
            ae_state, undecided, taken, current_lines, likelihood, likelihoods, states, entry
        )
        taken = likelier or taken
    return None if taken is None else (taken[1], taken[2])


def _likelier(
    ae_state: SearchState,
    candidates: Sequence[tuple[ln.Line, list[ln.Line], float]],
    default: tuple[ln.Line, list[ln.Line], float] | None,
    current: Sequence[ln.Line],
    likelihood: Likelihood,
    cache: dict[tuple[str, ...], float],
    states: set[str],
    entry: dict[str, object],
) -> tuple[ln.Line, list[ln.Line], float] | None:
    """Of ``candidates`` (lines no larger than the current one that simulate the closed model
    and fit their variable within the tolerance of it, yet not taken), the first whose
    equations ``likelihood`` rates above those the step takes otherwise (``default``, the
    simplest eligible line; None if none is eligible), or None: where the closed model
    and the held-out fit see noise, the likelihood with the states unknown still sees a line
    that holds (an identity such as v_d = V sin(delta - theta) against a stand-in that bends to
    the estimated states' errors) and a small term a line needs (an armature resistance). Only
    lines simpler than ``default`` are asked about, the simplest first, at most
    :data:`LIKELIHOOD_TRIALS`, each with the equations it would replace (one call: a likelihood
    may rate them side by side): the simplest eligible line's, or where none is eligible the
    current ones. (Rated against the current equations where an eligible line had already
    replaced them, a stand-in could win: on Table I's generator 31 seed 1, i_q's e''_d + v_f +
    V sin(delta - theta) rated 1,108 nats above the fit choice's lines and was taken over the
    stator equation, eligible, that rates 9,993 nats above it.) Each verdict goes into
    ``entry["likelihood"]``."""
    # the equations the step takes without the likelihood: a simpler line must beat them
    replaced = current if default is None else default[1]
    bound = None if default is None else _complexity(default[0], states)
    asked = sorted(
        (t for t in candidates if bound is None or _complexity(t[0], states) < bound),
        key=lambda t: (_complexity(t[0], states), settled(t[2])),
    )[:LIKELIHOOD_TRIALS]

    def rated(*sets: Sequence[ln.Line]) -> list[float]:
        """each set of lines rated, those not yet rated asked about together"""
        keys = [tuple(line.text for line in lines) for lines in sets]
        new = {k: _assemble(ae_state, lines) for k, lines in zip(keys, sets, strict=True)
               if k not in cache}  # fmt: skip
        cache.update((k, -np.inf) for k, eq in new.items() if eq is None)
        ready = [(k, eq) for k, eq in new.items() if eq is not None]
        if ready:
            values = likelihood([eq for _, eq in ready])
            cache.update((k, float(v)) for (k, _), v in zip(ready, values, strict=True))
        return [cache[k] for k in keys]

    verdicts, out = [], None
    for t in asked:
        now, then = rated(replaced, t[1])
        gain = then - now
        verdicts.append({"line": t[0].text, "gain": gain})
        if gain > 0:
            out = t
            break
    if verdicts:
        entry["likelihood"] = verdicts
    return out


def weighted_by_recording(
    state: SearchState, equations: Equations, *, iterations: int = 10, settle: float = 0.01
) -> tuple[SearchState, Equations, dict[str, object]]:
    """``equations`` refitted with every equation's samples weighted by the inverse of its
    error variance in their recording (iterated feasible generalised least squares).

    Least squares weights every sample alike, as if each recording were as noisy as the
    others. An algebraic equation's error is mostly the noise of its regressors passed through
    it (a stator current amplifies the noise of the rotor and terminal angles by 1/x'_d), and
    that noise scales with each recording's range: a recording whose machine slipped poles
    carries angles whose noise is tens of times the others', and its squared errors dominate
    the fit (coefficients shrink, stand-in terms soak up the noise). The error variance of each
    equation in each recording is estimated from the residuals of the current fit, the samples
    weighted by its inverse (normalised to mean 1 per equation), the equations refitted, and so
    on until no recording's weight changes by more than ``settle`` (relative) or after
    ``iterations`` refits: the maximum-likelihood fit with one error variance per equation and
    recording. With one recording, or where a variance is not positive and finite, nothing is
    reweighted. Returns the state whose problem carries the weights (``[targets, N]``; what
    follows fits on it), the refitted equations and a report: per target the weight of each
    recording's samples, and the refits made.

    The state equations too (a problem with a matched operator: the residuals are those the
    fit compares, the operator applied to the predictions): a state's noise is a share of its
    range, so the derivatives estimated from a recording whose machine slipped poles are tens
    of times noisier than the others', and so are its currents and voltages as regressors.
    """
    problem = state.problem
    if problem.groups is None:
        return state, equations, {}
    groups = np.asarray(problem.groups)
    labels = np.unique(groups)
    if len(labels) < 2:
        return state, equations, {}
    index = np.searchsorted(labels, groups)
    targets = np.asarray(problem.targets, dtype=float)
    base = np.stack([sample_weights(problem, j) for j in range(len(targets))])
    lines, _ = ln.split_lines(equations.source)
    current, previous = equations, None
    weighted = state
    per_recording: dict[str, list[float]] = {}
    refits = 0
    for _ in range(iterations):
        try:
            skeleton = _compile(current.source, state.contract)
        except SkeletonError:
            break
        variables = {n: problem.variables[n] for n in skeleton.arguments}
        pred = skeleton(variables, np.asarray(current.params))
        if problem.operator is not None:
            pred = problem.operator(jax.numpy.asarray(pred))
        pred = np.asarray(pred, dtype=float)
        weights = base.copy()
        shares = np.ones((len(targets), len(labels)))
        for j in range(len(targets)):
            r2 = (pred[j] - targets[j]) ** 2
            variance = np.bincount(index, base[j] * r2) / np.bincount(index, base[j])
            if not np.all(np.isfinite(variance) & (variance > 0)):
                continue
            w = base[j] / variance[index]
            weights[j] = w / np.mean(w)
            shares[j] = np.bincount(index, weights[j]) / np.bincount(index)
        if previous is not None and np.all(np.abs(shares / previous - 1) <= settle):
            break
        previous = shares
        problem_w = eqx.tree_at(
            lambda p: p.weights, problem, jax.numpy.asarray(weights), is_leaf=lambda x: x is None
        )
        trial = replace_state(state, problem=problem_w)
        refit = _assemble(trial, lines)
        if refit is None:
            break
        weighted, current, refits = trial, refit, refits + 1
        per_recording = {
            name: [float(x) for x in shares[j]] for j, name in enumerate(problem.target_names)
        }
    if not refits:
        return state, equations, {}
    return weighted, current, {"per_recording": per_recording, "refits": refits}


def _closed_loro(
    ae_state: SearchState, lines: Sequence[ln.Line], de: Equations,
    recordings: Sequence[Dataset], config: SelectionConfig,
    played_from: Sequence[Dataset] | None = None,
    fits: dict[tuple[int, str], np.ndarray | None] | None = None,
    windows: Sequence[tuple[int, int]] | None = None,
) -> tuple[float, np.ndarray]:  # fmt: skip
    """Mean NRMSE of the states of the closed model (state equations ``de``, algebraic lines
    ``lines``), each recording simulated with the algebraic lines fitted on the others, and
    each held-out recording's (or time block's) own mean ``[B]``; inf if a line does not
    compile or fit, or a rollout diverged. ``fits`` keeps each line's fold parameters between
    calls (a line that stays is not fitted again)."""
    closure = _closure(ae_state, lines, len(recordings), fits)
    if closure is None:
        return float("inf"), np.full(len(recordings), np.inf)
    program, rows = closure
    errors = dae_errors(
        de, program, ae_state.contract.targets, rows, recordings, config, played_from, windows
    )
    return float(np.mean(errors)), np.mean(errors, axis=1)


def _closed_trials(
    ae_state: SearchState, lines: Sequence[ln.Line], j: int, options: Sequence[ln.Line],
    de: Equations, recordings: Sequence[Dataset], config: SelectionConfig,
    played_from: Sequence[Dataset] | None = None,
    fits: dict[tuple[int, str], np.ndarray | None] | None = None,
    windows: Sequence[tuple[int, int]] | None = None,
) -> tuple[list[float], list[np.ndarray]]:  # fmt: skip
    """:func:`_closed_loro` of the closed model with each of ``options`` in place of line
    ``j`` of ``lines``: each option's mean error, and its held-out recordings' ``[B]``. The
    options that are sums of one-parameter terms run side by side as rows of one batch (line
    ``j`` holding all their terms, each row's parameters zero on the terms its option lacks);
    any other runs on its own."""
    fits = {} if fits is None else fits
    n = len(recordings)
    errors = [float("inf")] * len(options)
    held_out = [np.full(n, np.inf) for _ in options]
    renumbered = [ln.renumbered(line) for line in options]
    fitted = []  # (option index, its fold parameters [folds, P])
    for i, line in enumerate(renumbered):
        block = _fold_fit(ae_state, j, line, fits)
        if block is not None:
            fitted.append((i, block))
    union, maps = _union([renumbered[i] for i, _ in fitted])
    members = [
        (i, block, where)
        for (i, block), where in zip(fitted, maps, strict=True)
        if where is not None
    ]
    others = [i for (i, _), where in zip(fitted, maps, strict=True) if where is None]
    closure = None
    if members:
        trial = [*lines[:j], union, *lines[j + 1 :]]
        closure = _closure(ae_state, trial, n, fits, skip=j)
    if closure is None:
        others = [i for i, _ in fitted]
    else:
        program, rows = closure  # line j's columns are zeros: each member writes its own
        start = sum(ln.renumbered(line).n_params for line in lines[:j])
        batch = np.tile(rows, (len(members), 1))
        for m, (_, block, where) in enumerate(members):
            batch[m * n : (m + 1) * n, [start + w for w in where]] = _per_recording(
                block, ae_state, n
            )
        k = len(members)
        err = dae_errors(
            de, program, ae_state.contract.targets, batch, list(recordings) * k, config,
            None if played_from is None else list(played_from) * k,
            None if windows is None else list(windows) * k,
        )  # fmt: skip
        means, per_row = err.reshape(k, -1).mean(axis=1), err.reshape(k, n, -1).mean(axis=2)
        for m, (i, _, _) in enumerate(members):
            errors[i], held_out[i] = float(means[m]), per_row[m]
    for i in others:
        trial = [*lines[:j], options[i], *lines[j + 1 :]]
        errors[i], held_out[i] = _closed_loro(
            ae_state, trial, de, recordings, config, played_from, fits, windows
        )
    return errors, held_out


def _fold_fit(
    ae_state: SearchState, j: int, line: ln.Line, fits: dict[tuple[int, str], np.ndarray | None]
) -> np.ndarray | None:
    """Line ``j``'s (renumbered) parameters fitted with each fold left out, ``[folds, P]``
    (None if it does not compile or fit), kept in ``fits`` (a line is fitted once)."""
    if (j, line.text) not in fits:
        _, params, usable = _usable_fits(ae_state, j, [line])
        fits[j, line.text] = params[0, :, : line.n_params] if usable else None
    return fits[j, line.text]


def _closure(
    ae_state: SearchState, lines: Sequence[ln.Line], n: int,
    fits: dict[tuple[int, str], np.ndarray | None] | None = None,
    skip: int | None = None,
) -> tuple[interp.Program, np.ndarray] | None:  # fmt: skip
    """The algebraic lines as one program and their parameters fitted with each fold left out,
    one row per recording (``n``, :func:`_per_recording`); None if a line does not compile or
    fit. ``fits``: as in :func:`_closed_loro`. Line ``skip`` is not fitted: its parameters are
    zeros (for the caller to fill in)."""
    fits = {} if fits is None else fits
    lines = [ln.renumbered(line) for line in lines]
    blocks = []
    for j, line in enumerate(lines):
        if j == skip:
            blocks.append(np.zeros((len(np.unique(_folds(ae_state))), line.n_params)))
            continue
        block = _fold_fit(ae_state, j, line, fits)
        if block is None:
            return None
        blocks.append(block)
    contract = ae_state.contract
    source = ln.assemble(contract.function_name, contract.arguments, lines, contract.outputs)
    try:
        program = interp.lower(source, n_outputs=len(lines))
    except (interp.LoweringError, ValueError):
        return None
    return program, _per_recording(np.concatenate(blocks, axis=1), ae_state, n)


# ----------------------------------------------------------------------------------------------
# the state equations chosen again in the closed model


def _union(lines: Sequence[ln.Line]) -> tuple[ln.Line, list[list[int] | None]]:
    """One line holding every one-parameter term of ``lines`` (``p[u] * term``), and for each
    line the union's parameter index of each of its parameters (in the order
    :func:`jaxdmd.lines.renumbered` numbers them), or None where a line is not a sum of
    distinct one-parameter terms (it is simulated on its own)."""
    keys: dict[str, int] = {}
    union: ln.Line | None = None
    maps: list[list[int] | None] = []
    for line in lines:
        line = ln.renumbered(line)
        parts = ln.summands(line.expr)
        index = []
        for part in parts:
            found = ln.param_indices(part)
            if len(found) != 1:
                break
            index.append(found[0])
        texts = [_terms(ln.Line(part, 1)).pop() for part in parts]
        if (
            len(index) != len(parts)
            or len(set(texts)) != len(texts)
            or sorted(index) != list(range(line.n_params))
        ):
            maps.append(None)
            continue
        where = [0] * line.n_params
        for part, text, i in zip(parts, texts, index, strict=True):
            if text not in keys:
                term = ln.renumbered(ln.Line(ln.copy_tree(part), 1))
                union = term if union is None else ln.with_summand(union, term)
                keys[text] = len(keys)
            where[i] = keys[text]
        maps.append(where)
    return (union if union is not None else ln.Line(ast.Constant(0.0), 0)), maps


def _states_closed_errors(
    de_state: SearchState, j: int, lines: Sequence[ln.Line], fixed: Sequence[ln.Line],
    targets: Sequence[str], closure: tuple[interp.Program, Sequence[str], np.ndarray],
    recordings: Sequence[Dataset], config: SelectionConfig,
    played_from: Sequence[Dataset] | None = None,
    windows: Sequence[tuple[int, int]] | None = None,
) -> np.ndarray:  # fmt: skip
    """Each line's error as state equation ``j`` of the closed model: every state integrated
    (the other state equations ``fixed``, their parameters written in), every algebraic
    variable computed by the closure (program, targets, per-recording parameter rows), the
    line fitted with each recording (or time block) left out and the held-out one simulated;
    the mean NRMSE of all states.

    The candidates run side by side as rows of one batch: the lines that are sums of
    one-parameter terms share one program whose equation ``j`` holds all their terms, each
    row's parameters zero on the terms its line lacks; any other line runs on its own."""
    errors = np.full(len(lines), np.inf)
    lines = [ln.renumbered(line) for line in lines]
    _, params, usable = _usable_fits(de_state, j, lines)
    if not usable:
        return errors
    b = len(recordings)
    union, members, wide, alone = _side_by_side(usable, lines, params, de_state, b)
    groups = [
        (lines[i], [i], _per_recording(params[c, :, : lines[i].n_params], de_state, b))
        for c, i in alone
    ]
    if members:
        groups.append((union, members, wide))
    ae_program, ae_targets, ae_rows = closure
    source_of_play = list(recordings) if played_from is None else list(played_from)
    for line, indices, rows in groups:
        equations = [*fixed[:j], line, *fixed[j:]]
        used = set().union(*(e.variables() for e in equations))
        arguments = [
            *targets, *(a for a in de_state.contract.arguments if a in used and a not in targets)
        ]  # fmt: skip
        outputs = [f"y{k}" for k in range(len(equations))]
        try:
            program = interp.lower(
                ln.assemble("closed", arguments, equations, outputs), n_outputs=len(outputs)
            )
        except (interp.LoweringError, ValueError):
            continue
        closed = (ae_program, ae_targets, np.tile(ae_rows, (len(indices), 1)))
        err = _batch_errors(
            program, targets, rows, source_of_play, recordings, config, windows, algebraic=closed
        )
        for i, e in zip(indices, err, strict=True):
            errors[i] = float(e)
    return errors


def front_lines(report: dict[str, object], target: str) -> list[ln.Line]:
    """The lines of ``target``'s Pareto front in a :func:`select_by_simulation` report."""
    entry = report.get("equations", {}).get(target, {})  # type: ignore[union-attr]
    out = []
    for point in entry.get("pareto", ()):
        expr = ast.parse(point["line"], mode="eval").body
        out.append(ln.renumbered(ln.Line(expr, 0)))
    return out


def select_states_closed(
    de_state: SearchState,
    de: Equations,
    ae_state: SearchState,
    ae: Equations,
    recordings: Sequence[Dataset],
    config: SelectionConfig | None = None,
    played_from: Sequence[Dataset] | None = None,
    starts: Sequence[Sequence[ln.Line]] = (),
) -> tuple[Equations, dict[str, object]]:
    """The state equations chosen again in the closed model, once the algebraic equations are.

    :func:`select_by_simulation` chooses each state equation with the measured algebraic
    variables played in. There a stand-in (an algebraic variable in place of a state term it
    is nearly collinear with on the training data, ``v_d`` for ``e''_d``) simulates about as
    well as the true term, since the measured variable is exact; closed, the stand-in is
    computed from the simulated states and its error feeds back. So each state equation in
    turn is chosen again with every state integrated and every algebraic variable computed by
    ``ae`` (its lines fitted with each recording left out): the candidates are its current
    line, ``starts[j]`` (the played-in Pareto front) and the archive's best lines, then the
    local search in term space (:func:`_local_search`) with the swap move, since adding the
    true term or dropping the stand-in alone rarely helps while the other stays. A line
    replaces the current one only if the closed model then simulates the held-out recordings
    better by more than ``tolerance`` (a simpler line that is merely as good changed the test
    error either way on Table I: the lines are already the played-in choice), and if it
    simulates alone with the measured algebraic variables played in (:func:`_single_errors`)
    within ``tolerance`` of the current line: a line that only simulates well closed may
    compensate an algebraic line's error (d omega/dt writing out a power the P_e line gets
    wrong) instead of being right; of those, the simplest within ``tolerance`` of the best.
    The equations are refitted on every recording after each change.

    ``recordings``, ``played_from``: as in :func:`select_algebraic`. Returns the equations and a
    report: per state equation the closed error of its current line, the candidates, the
    Pareto front and the choice; the equations changed.
    """
    config = config or SelectionConfig()
    recordings = list(recordings)
    if not _shared_grid(recordings):
        return de, {"skipped": "the recordings do not share a time grid"}
    contract = de.contract
    targets = tuple(contract.targets)
    states = {v.name for v in contract.states}
    held = _held_out(de_state, recordings)
    held_ae = _held_out(ae_state, recordings, played_from)
    ae_lines, _ = ln.split_lines(ae.source)
    closure = _closure(held_ae.state, ae_lines, len(held.recordings))
    if closure is None:
        return de, {"skipped": "the algebraic equations do not fit with a fold left out"}
    ae_program, ae_rows = closure
    ae_targets = tuple(ae.contract.targets)
    archived = _archive_lines(de_state)
    report: dict[str, object] = {"held_out": held.label, "equations": {}}
    changed: list[str] = []
    current = de
    for j, target in enumerate(targets):
        lines, mappings = ln.split_lines(current.source)
        values = np.asarray(current.params, dtype=float)
        fixed = [
            ln.Line(_with_constants(line, values[list(m)]), 0)
            for k, (line, m) in enumerate(zip(lines, mappings, strict=True))
            if k != j
        ]

        def score(new: list[ln.Line], j: int = j, fixed: list[ln.Line] = fixed) -> np.ndarray:
            return _states_closed_errors(
                held.state, j, new, fixed, targets,
                (ae_program, ae_targets, ae_rows), held.recordings, config,
                held_ae.played_from, held.windows,
            )  # fmt: skip

        first: dict[frozenset[str], ln.Line] = {}
        for line in [
            lines[j],
            *(starts[j] if j < len(starts) else ()),
            *_candidate_lines(archived, j, lines[j], config.candidates),
        ]:
            first.setdefault(_key(line), line)
        candidates = list(first.values())
        errors = score(candidates)
        before = float(errors[0])
        pool_j = _term_pool(archived, j, config.terms)
        candidates, errors = _local_search(
            candidates, errors, pool_j, score, config, states, swap=True
        )
        if not np.isfinite(np.min(errors)):
            report["equations"][target] = {"kept": "no candidate simulates closed"}  # type: ignore[index]
            continue
        entry = _choose(candidates, errors, config, states)[1]
        entry["dae_nrmse_current"] = before
        best = float(np.min(errors))
        eligible = [
            i for i, e in enumerate(errors)
            if e <= best * (1 + config.tolerance) and e * (1 + config.tolerance) < before
        ]  # fmt: skip
        if eligible:  # and no worse by more than the tolerance with the algebraic played in
            played = _single_errors(
                held.state, j, [lines[j], *(candidates[i] for i in eligible)], held.recordings,
                config, held.windows,
            )  # fmt: skip
            entry["played_in_nrmse_current"] = float(played[0])
            eligible = [
                i for i, e in zip(eligible, played[1:], strict=True)
                if e <= played[0] * (1 + config.tolerance)
            ]  # fmt: skip
        entry["chosen"] = lines[j].text
        if eligible:
            pick = min(eligible, key=lambda i: (_complexity(candidates[i], states),
                                                settled(errors[i])))  # fmt: skip
            trial = _assemble(de_state, [*lines[:j], candidates[pick], *lines[j + 1 :]])
            if trial is not None:
                current = trial
                changed.append(target)
                entry["chosen"] = candidates[pick].text
                entry["dae_nrmse"] = float(errors[pick])
        report["equations"][target] = entry  # type: ignore[index]
    report["changed"] = changed
    return current, report


# ----------------------------------------------------------------------------------------------
# several searches: one pool of candidates, and how often each term is chosen


def pool(states: Sequence[SearchState]) -> SearchState:
    """One state whose archive holds every search's islands and whose library is the union of
    the searches' libraries (the first state's data, key and configuration): the candidates
    :func:`jaxdmd.search.final_equations` and :func:`select_by_simulation` choose from."""
    from jaxdmd import archive as arc
    from jaxdmd.search import replace_state

    first = states[0]
    if len(states) == 1:
        return first
    library = list(first.contract.library)
    for state in states[1:]:
        for v in state.contract.library:
            if v.name not in {u.name for u in library}:
                library.append(v)
    islands = tuple(isl for state in states for isl in state.archive.islands)
    config = dataclasses.replace(first.archive.config, n_islands=len(islands))
    joined = tuple(dict.fromkeys(j for state in states for j in state.joined))
    return replace_state(
        first,
        contract=dataclasses.replace(first.contract, library=tuple(library)),
        archive=arc.Archive(islands, config),
        joined=joined,
    )


def _terms(line: ln.Line) -> set[str]:
    """The summands of a line with its parameters blanked (``p[3] * (omega - 1)`` and
    ``p[0] * (omega - 1)`` are the same term)."""
    return set(_text_terms(line.text))


class _Blank(ast.NodeTransformer):
    def visit_Subscript(self, node: ast.Subscript) -> ast.expr:
        if isinstance(node.value, ast.Name) and node.value.id == "p":
            return ast.Name("p", ast.Load())
        return self.generic_visit(node)


@functools.lru_cache(maxsize=1 << 16)
def _text_terms(text: str) -> frozenset[str]:
    """:func:`_terms` of a line's text (the selection asks for the same lines' terms thousands
    of times)."""
    expr = ast.parse(text, mode="eval").body
    return frozenset(ast.unparse(_Blank().visit(s)) for s in ln.summands(expr))


def inclusion_frequency(
    chosen: Equations, per_search: Sequence[Equations]
) -> dict[str, dict[str, float]]:
    """For each equation of ``chosen``, each of its terms with the share of the searches whose
    own final equation holds that term (1.0: every search chose it; a term only the pool found
    has 0.0)."""
    lines, _ = ln.split_lines(chosen.source)
    theirs = [ln.split_lines(eq.source)[0] for eq in per_search]
    out: dict[str, dict[str, float]] = {}
    for j, target in enumerate(chosen.contract.targets):
        terms = _terms(lines[j])
        sets = [_terms(other[j]) for other in theirs]
        out[target] = {t: sum(t in s for s in sets) / max(1, len(sets)) for t in sorted(terms)}
    return out
