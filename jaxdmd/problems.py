"""Each loop's problem from recordings: what the DE and AE loops fit, and how.

- :func:`de_problem`: targets are the state derivatives (estimated, matched to the estimator's
  smoothing by :func:`matched_operator`, optionally weighted by :func:`noise_weights`) or the
  states' increments over windows (the integral form, :func:`integral_operator`); the states are
  always arguments; the variable library starts empty and may grow from the catalog (every
  non-state channel).
- :func:`ae_problem`: targets are the algebraic variables the DE loop brought in; inputs the DE
  loop used stay exogenous (they start the AE library); the catalog is the boundary (terminal
  voltage magnitude and angle), so that the discovered DAE closes on the boundary.
- :func:`estimator_gains`: how the default derivative estimator passes white noise, per sample.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from jaxdmd.data import (
    Dataset,
    estimator_band,
    event_samples,
    matched_filter,
    stack_samples,
)
from jaxdmd.fit import Operator
from jaxdmd.prompts import Contract, Variable
from jaxdmd.search import Problem


def _variables(ds: Dataset, names: Sequence[str]) -> tuple[Variable, ...]:
    return tuple(Variable(n, ds.role(n), ds.unit(n)) for n in names)  # type: ignore[arg-type]


def _stack(datasets: Sequence[Dataset]) -> dict[str, jax.Array]:
    names = datasets[0].names
    for ds in datasets[1:]:
        if ds.names != names:
            raise ValueError(f"recordings differ in their channels: {ds.label or '?'}")
    return {k: jnp.asarray(v) for k, v in stack_samples(datasets, names).items()}


def _groups(datasets: Sequence[Dataset]) -> jax.Array:
    """The recording index of every concatenated sample."""
    return jnp.asarray(np.concatenate([np.full(ds.n_samples, i) for i, ds in enumerate(datasets)]))


def matched_operator(datasets: Sequence[Dataset]) -> Operator:
    """The smoothing matched to the default derivative estimator, over concatenated recordings.

    Each recording gets :func:`jaxdmd.data.matched_filter` of its own time grid and events
    (computed once per distinct grid), shifted to its place in the concatenation.
    """
    cache: dict[tuple[bytes, tuple[float, ...]], tuple[np.ndarray, np.ndarray]] = {}
    indices, weights, offset = [], [], 0
    for ds in datasets:
        key = (np.asarray(ds.t).tobytes(), ds.events)
        if key not in cache:
            cache[key] = matched_filter(ds.t, events=ds.events)
        index, weight = cache[key]
        indices.append(index + offset)
        weights.append(weight)
        offset += ds.n_samples
    width = max(i.shape[1] for i in indices)  # pad every band to the widest (weight 0)
    index = np.concatenate(
        [np.pad(i, [(0, 0), (0, width - i.shape[1])], mode="edge") for i in indices]
    )
    weight = np.concatenate([np.pad(w, [(0, 0), (0, width - w.shape[1])]) for w in weights])
    return Operator(index, weight)


def integral_operator(datasets: Sequence[Dataset], width: float) -> tuple[Operator, np.ndarray]:
    """The integral (weak) form of state equations over concatenated recordings.

    Row i integrates a prediction over ``[t_i, t_i + width]`` (trapezoid rule, never across a
    recording's end; near the end the window is shorter, and the last sample's row covers the
    interval before it). Returns the operator and, for each row, the sample index pair
    ``(first, last)`` of its window, so that the targets are ``x[last] - x[first]``: no
    derivative estimate is needed, and the noise of the states enters only at the two ends.
    """
    if width <= 0:
        raise ValueError(f"the integration window must be positive, got {width}")
    rows_index, rows_weight, ends, offset = [], [], [], 0
    for ds in datasets:
        t = np.asarray(ds.t, dtype=np.float64)
        n = t.shape[0]
        if n < 2:
            raise ValueError(f"recording {ds.label or '?'} has fewer than two samples")
        first = np.arange(n)
        last = np.minimum(np.searchsorted(t, t + width, side="right") - 1, n - 1)
        last = np.maximum(last, first + 1)
        first = np.where(last > n - 1, n - 2, first)
        last = np.minimum(last, n - 1)
        span = int(np.max(last - first)) + 1
        k = first[:, None] + np.arange(span)[None, :]
        inside = k <= last[:, None]
        k = np.where(inside, k, last[:, None])
        dt = np.diff(t)
        # trapezoid: sample k gets (dt_{k-1} + dt_k) / 2 of the intervals inside the window;
        # an interval that ends at an event (a fault applied or cleared: the sample there holds
        # the values after the jump, the algebraic variables jump) is integrated by its left
        # end alone: averaging across the jump would be wrong by half the jump
        at_event = event_samples(t, ds.events)  # [n]
        ends_at_event = at_event[1:]  # interval j = (t_j, t_{j+1}]
        share_left = np.where(ends_at_event, 1.0, 0.5)
        share_right = np.where(ends_at_event, 0.0, 0.5)
        left = np.where(k > first[:, None], (dt * share_right)[np.maximum(k - 1, 0)], 0.0)
        right = np.where(k < last[:, None], (dt * share_left)[np.minimum(k, n - 2)], 0.0)
        rows_index.append(k + offset)
        rows_weight.append(np.where(inside, left + right, 0.0))
        ends.append(np.stack([first, last], axis=1) + offset)
        offset += n
    width_max = max(i.shape[1] for i in rows_index)
    index = np.concatenate(
        [np.pad(i, [(0, 0), (0, width_max - i.shape[1])], mode="edge") for i in rows_index]
    )
    weight = np.concatenate([np.pad(w, [(0, 0), (0, width_max - w.shape[1])]) for w in rows_weight])
    return Operator(index, weight), np.concatenate(ends)


def noise_weights(datasets: Sequence[Dataset]) -> np.ndarray:
    """Sample weights inverse to the noise the default derivative estimator passes, [n].

    The estimate is linear in the samples, ``D @ x``; white noise of variance sigma^2 on ``x``
    gives the estimate at sample i the variance ``sigma^2 * sum_j D_ij^2``. Right after an event
    the estimator's window is short and this gain is large (hundreds of times the settled
    value); weighting the squared errors by its inverse is generalised least squares for
    independent errors. The weights are normalised to mean 1 over all recordings.
    """
    cache: dict[tuple[bytes, tuple[float, ...]], np.ndarray] = {}
    parts = []
    for ds in datasets:
        key = (np.asarray(ds.t).tobytes(), ds.events)
        if key not in cache:
            cache[key] = 1.0 / estimator_gains(ds).derivative_square
        parts.append(cache[key])
    w = np.concatenate(parts)
    return w / w.mean()


def de_problem(
    datasets: Sequence[Dataset],
    system: str = "synchronous generator",
    *,
    matched: bool = False,
    states: Sequence[str] | None = None,
    library: Sequence[str] = (),
    groups: np.ndarray | None = None,
    integral: float | None = None,
    weighted: bool = False,
    smooth: bool = False,
) -> tuple[Problem, Contract]:
    """The DE loop's problem: state derivatives from every recording, the catalog, the contract.

    With ``matched``, the recordings' derivatives must be the default estimates of
    :func:`jaxdmd.data.differentiate` (``Dataset.create`` without derivatives, or
    ``with_estimated_derivatives()``): predictions are then smoothed like the estimates
    (:func:`matched_operator`), which removes the estimator's bias at fast transients.

    ``states`` (default: every state channel) are the targets; ``library`` the variables the
    search starts with; every other channel (other states included) is the catalog. ``groups``
    overrides the recording index of each sample used for cross-validation. With ``integral``
    (seconds), the equations are fitted in their integral form (:func:`integral_operator`):
    targets are the states' increments over windows of that width, derivatives are not used.
    With ``weighted`` (same requirement as ``matched``), every sample is weighted by the
    inverse of the noise the estimator passes there (:func:`noise_weights`). With ``smooth``,
    the states are replaced by their smoothed estimates (as in :func:`ae_problem`) before
    anything else: in the integral form this cuts the noise of the increments and of the
    regressors (errors in variables bias the coefficients towards zero).
    """
    datasets = list(datasets)
    if smooth:
        datasets = [ds.with_estimated_derivatives(smooth=True) for ds in datasets]
    first = datasets[0]
    if not first.state_names:
        raise ValueError("the data have no state channels (role 'state')")
    states = tuple(first.state_names if states is None else states)
    for name in (*states, *library):
        if name not in first:
            raise ValueError(f"the data have no channel {name!r}; they have {list(first.names)}")
    for name in states:
        if first.role(name) != "state":
            raise ValueError(
                f"{name!r} is not a state channel of the data (role {first.role(name)!r})"
            )
    variables = _stack(datasets)
    operator = matched_operator(datasets) if matched else None
    if integral is not None:
        operator, ends = integral_operator(datasets, integral)
        targets = jnp.stack([variables[s][ends[:, 1]] - variables[s][ends[:, 0]] for s in states])
    else:
        targets = jnp.stack(
            [jnp.asarray(np.concatenate([ds.derivative(s) for ds in datasets])) for s in states]
        )
    others = [n for n in first.names if n not in states and n not in library]
    problem = Problem(
        variables=variables,
        targets=targets,
        target_names=states,
        catalog=_variables(first, others),
        operator=operator,
        groups=_groups(datasets) if groups is None else jnp.asarray(groups),
        weights=jnp.asarray(noise_weights(datasets)) if weighted else None,
    )
    contract = Contract(
        loop="DE",
        targets=states,
        states=_variables(first, states),
        library=_variables(first, library),
        function_name="equation",
        system=system,
    )
    return problem, contract


def ae_problem(
    datasets: Sequence[Dataset],
    de_contract: Contract,
    system: str = "synchronous generator",
    *,
    smooth: bool = False,
) -> tuple[Problem, Contract]:
    """The AE loop's problem: explicit equations for the algebraic variables the DE loop uses.

    With ``smooth``, the states (the AE loop's regressors) are replaced by their smoothed
    estimates (the derivative estimator's, ``Dataset.with_estimated_derivatives(smooth=True)``).
    For noisy states this matters: an algebraic equation such as a stator current amplifies the
    noise of its regressors (by 1/x'' for a machine), and least squares on noisy regressors
    shrinks and mixes the coefficients (errors in variables); smoothing cuts that noise.
    """
    datasets = list(datasets)
    if smooth:
        datasets = [ds.with_estimated_derivatives(smooth=True) for ds in datasets]
    first = datasets[0]
    targets = tuple(v.name for v in de_contract.library if v.role == "algebraic")
    if not targets:
        raise ValueError("the DE loop used no algebraic variable: there is nothing to close")
    inputs = tuple(v for v in de_contract.library if v.role == "input")
    boundary = [n for n in first.names if first.role(n) == "boundary"]
    spare_inputs = [
        n for n in first.names if first.role(n) == "input" and n not in {v.name for v in inputs}
    ]
    variables = _stack(datasets)
    problem = Problem(
        variables=variables,
        targets=jnp.stack([variables[t] for t in targets]),
        target_names=targets,
        catalog=_variables(first, [*boundary, *spare_inputs]),
        groups=_groups(datasets),
    )
    contract = Contract(
        loop="AE",
        targets=targets,
        states=de_contract.states,
        library=inputs,
        function_name="algebraic",
        system=system,
    )
    return problem, contract


@dataclass(frozen=True)
class EstimatorGains:
    """How the default estimator (``jaxdmd.data.differentiate``: smoothed values ``S x``,
    derivatives ``D x``) passes white noise, per sample of one recording, [n] each."""

    smoother_diagonal: np.ndarray  # S_ii
    smoother_square: np.ndarray  # sum_k S_ik^2
    derivative_square: np.ndarray  # sum_k D_ik^2


def estimator_gains(ds: Dataset, block: int = 2000) -> EstimatorGains:
    """The :class:`EstimatorGains` of ``ds``'s time grid and events.

    S and D are band matrices (:func:`jaxdmd.data.estimator_band`). The sums of squares are
    taken over dense slices of ``block`` columns (the rows the block meets), as the former
    construction from unit samples summed them, so they are the same to the last bit: memory
    stays (block + band) x block and time is linear in the number of samples.
    """
    lo, smooth, deriv = estimator_band(ds.t, events=ds.events)
    n, width = smooth.shape
    rows_all = np.arange(n)
    offset = rows_all - lo
    inside = (offset >= 0) & (offset < width)
    diagonal = np.where(inside, smooth[rows_all, np.clip(offset, 0, width - 1)], 0.0)
    s_square, d_square = np.zeros(n), np.zeros(n)
    hi = lo + width  # one past the band (the padding beyond n holds zeros)
    for start in range(0, n, block):
        stop = min(n, start + block)
        rows = np.flatnonzero((lo < stop) & (hi > start))
        cols = lo[rows, None] + np.arange(width)[None, :] - start  # [r, width] in the block
        keep = (cols >= 0) & (cols < stop - start)
        r_idx = np.broadcast_to(np.arange(rows.size)[:, None], cols.shape)[keep]
        for band, total in ((smooth, s_square), (deriv, d_square)):
            dense = np.zeros((rows.size, stop - start))
            dense[r_idx, cols[keep]] = band[rows][keep]
            total[rows] += np.sum(dense**2, axis=1)
    return EstimatorGains(diagonal, s_square, d_square)
