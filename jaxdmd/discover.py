"""Discovery from datasets: build each loop's problem, run loops, hand the DE result to the AE loop.

This is the thin layer between measured recordings (:class:`jaxdmd.data.Dataset`) and the pure
search (:mod:`jaxdmd.search`):

- :func:`de_problem`: targets are the state derivatives; the states are always arguments; the
  variable library starts empty and may grow from the catalog (every non-state channel).
- :func:`ae_problem`: targets are the algebraic variables the DE loop brought in; inputs the DE
  loop used stay exogenous (they start the AE library); the catalog is the boundary (terminal
  voltage magnitude and angle), so that the discovered DAE closes on the boundary.
- :func:`smoothed_states`, :func:`model_states`: the AE loop's regressors, the noisy states
  replaced by an estimate (a generic smoother, or a Kalman smoother with the discovered state
  equations); :func:`refit_bias_compensated` corrects the AE fit for the noise they keep.
- :func:`run_loop`: the plain Python loop over ``prompts``, a proposer and ``step``, with a
  callback per round and the state written atomically after each round (resumable).
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxdmd import lines as ln
from jaxdmd import search
from jaxdmd.data import Dataset, event_samples, matched_filter, stack_samples
from jaxdmd.estimate import StateEstimate, model_smoother
from jaxdmd.fit import FitConfig, Operator
from jaxdmd.prompts import Contract, Variable
from jaxdmd.proposers import Proposer
from jaxdmd.search import Equations, Problem, RoundReport, SearchConfig, SearchState


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


def refit_integral(
    equations: Equations,
    datasets: Sequence[Dataset],
    width: float,
    key: jax.Array,
    config: FitConfig | None = None,
) -> tuple[Equations, tuple[float, ...]]:
    """The DE loop's final equations with their parameters refitted in the integral form.

    The structure comes from the search; the parameters are fitted again to the increments of
    the smoothed states over ``width``-second windows (:func:`de_problem` with ``integral`` and
    ``smooth``), which needs no derivative estimate: on the benchmark the true structure's
    largest coefficient error falls from 2.3 % (weighted derivatives) to 1.5 %
    (``benchmarks/oracle.py``). Returns the refitted equations (their ``losses`` and ``score``
    remain the search's, in its own form) and the integral-form NMSE of each equation. If the
    refit fails the equations are returned unchanged, with NaN for those NMSEs.
    """
    contract = equations.contract
    problem, _ = de_problem(datasets, states=contract.targets, integral=width, smooth=True)
    (result,) = search.fit_problem([equations.skeleton()], problem, key, config)
    if result.error is not None:
        return equations, tuple(float("nan") for _ in contract.targets)
    refit = dataclasses.replace(equations, params=tuple(float(x) for x in result.params))
    return refit, tuple(float(x) for x in result.losses)


@dataclass(frozen=True)
class EstimatorGains:
    """How the default estimator (``jaxdmd.data.differentiate``: smoothed values ``S x``,
    derivatives ``D x``) passes white noise, per sample of one recording, [n] each."""

    smoother_diagonal: np.ndarray  # S_ii
    smoother_square: np.ndarray  # sum_k S_ik^2
    derivative_square: np.ndarray  # sum_k D_ik^2


def estimator_gains(ds: Dataset, block: int = 2000) -> EstimatorGains:
    """The :class:`EstimatorGains` of ``ds``'s time grid and events.

    S and D are linear in the samples, so they are built from unit samples, a block of columns
    at a time: memory stays n x block.
    """
    from jaxdmd.data import differentiate

    n = ds.n_samples
    diagonal, s_square, d_square = np.zeros(n), np.zeros(n), np.zeros(n)
    for start in range(0, n, block):
        cols = np.arange(start, min(n, start + block))
        unit = np.zeros((n, cols.size))
        unit[cols, np.arange(cols.size)] = 1.0
        s_cols, d_cols = differentiate(ds.t, unit, events=ds.events)  # S[:, cols], D[:, cols]
        diagonal[cols] = s_cols[cols, np.arange(cols.size)]
        s_square += np.sum(s_cols**2, axis=1)
        d_square += np.sum(d_cols**2, axis=1)
    return EstimatorGains(diagonal, s_square, d_square)


def _residual_variance(x: np.ndarray, smooth: np.ndarray, gains: EstimatorGains) -> np.ndarray:
    """The white-noise variance of each column of ``x`` [n, k] from the smoother's residual.

    With x = s + e, E|x - Sx|^2 = sigma^2 sum_i (1 - 2 S_ii + sum_k S_ik^2) for a signal the
    smoother passes. What it does not pass (a wrapped angle, a fast transient) counts as noise,
    so the estimate suits smooth channels such as the states.
    """
    passed = np.sum(1.0 - 2.0 * gains.smoother_diagonal + gains.smoother_square)
    return np.sum((x - smooth) ** 2, axis=0) / passed


def smoothed_states(datasets: Sequence[Dataset], noisy: Sequence[str]) -> list[StateEstimate]:
    """The channels ``noisy`` (states) replaced by the default smoother's estimates.

    Their white-noise variance is estimated per recording from the smoother's residual
    (:func:`_residual_variance`); the estimates keep the share ``sum_k S_ik^2`` of it, which is
    the (diagonal) covariance returned.
    """
    noisy = tuple(noisy)
    out = []
    for ds in datasets:
        smooth = ds.with_estimated_derivatives(smooth=True)
        gains = estimator_gains(ds)
        x, xs = (np.stack([np.asarray(d[a], dtype=float) for a in noisy], 1) for d in (ds, smooth))
        sigma2 = _residual_variance(x, xs, gains)
        covariance = gains.smoother_square[:, None, None] * np.diag(sigma2)[None]
        noise = dict(zip(noisy, sigma2.tolist(), strict=True))
        out.append(
            StateEstimate(
                ds.with_values(dict(zip(noisy, xs.T, strict=True))),
                noisy,
                covariance,
                {},
                noise,
                float("nan"),
            )
        )
    return out


def model_states(de: Equations, datasets: Sequence[Dataset]) -> list[StateEstimate]:
    """The states estimated with the discovered state equations as process model
    (:func:`jaxdmd.estimate.model_smoother`), their noise variance estimated per recording as in
    :func:`smoothed_states`. Raises ``ValueError`` if the estimate is not finite."""
    states = tuple(de.contract.targets)
    noise = [e.noise for e in smoothed_states(datasets, states)]
    estimates = model_smoother(de.skeleton(), de.params, states, datasets, noise)
    for e in estimates:
        if not (np.all(np.isfinite(e.covariance)) and np.all(np.isfinite(e.dataset.values))):
            raise ValueError(f"the state estimate of {e.dataset.label!r} is not finite")
    return estimates


def refit_bias_compensated(
    equations: Equations, estimates: Sequence[StateEstimate]
) -> tuple[Equations, dict[str, str]]:
    """The AE loop's equations refitted by bias-compensated least squares.

    Least squares on noisy regressors is biased towards zero and mixes the coefficients
    (errors in variables): with features G of the regressors, E[G'G] = G0'G0 + C, where C is
    the covariance of the features' noise. The regressors are the recordings of ``estimates``
    (states replaced by an estimate, :func:`smoothed_states` or :func:`model_states`), whose
    covariance per sample is propagated to the features through their Jacobian in the states
    (first order); each equation that is affine in its parameters is refitted as
    p = (G'G - C)^-1 G'y. The other channels are taken as measured without noise. An equation
    that is not affine in p, or whose corrected matrix is not positive definite, keeps its
    parameters. Returns the equations and, per target, what was done.
    """

    lines, mappings = ln.split_lines(equations.source)
    params = np.array(equations.params, dtype=float)
    contract = equations.contract
    report: dict[str, str] = {}
    for target, line, mapping in zip(contract.targets, lines, mappings, strict=True):
        skeleton = search._line_skeleton(contract, line)
        names = tuple(skeleton.arguments)
        n_p = max(1, line.n_params)

        def value(args: jax.Array, p: jax.Array, skeleton=skeleton) -> jax.Array:
            out = skeleton.fn(*args, p)
            return jnp.asarray(out[0] if isinstance(out, tuple | list) else out, jnp.float64)

        features = jax.jit(jax.vmap(jax.jacfwd(value, argnums=1), in_axes=(0, None)))  # [n, P]
        sensitivity = jax.jit(jax.vmap(jax.jacfwd(jax.jacfwd(value, argnums=1)), in_axes=(0, None)))
        offsets = jax.jit(jax.vmap(value, in_axes=(0, None)))
        gram = correction = 0.0
        cross = 0.0
        affine = True
        for estimate in estimates:
            ds = estimate.dataset
            args = np.stack([np.asarray(ds[a], dtype=float) for a in names], axis=1)
            zero, one = jnp.zeros(n_p), jnp.ones(n_p)
            g = np.asarray(features(args, zero))
            if not np.allclose(g, np.asarray(features(args, one)), rtol=1e-9, atol=1e-12):
                affine = False
                break
            offset = np.asarray(offsets(args, zero))
            noisy = [names.index(s) for s in estimate.states if s in names]
            rows = [estimate.states.index(names[a]) for a in noisy]
            jac = np.asarray(sensitivity(args, zero))[:, :, noisy]  # [n, P, A] d feature/d state
            cov = estimate.covariance[:, rows][:, :, rows]  # [n, A, A]
            y = np.asarray(ds[target], dtype=float) - offset
            gram = gram + g.T @ g
            cross = cross + g.T @ y
            correction = correction + np.einsum("npa,nab,nqb->pq", jac, cov, jac)
        if not affine:
            report[target] = "kept: not affine in its parameters"
            continue
        corrected = gram - correction
        eig = np.linalg.eigvalsh(corrected)
        if not np.all(np.isfinite(eig)) or eig.min() <= 1e-12 * max(eig.max(), 1e-300):
            report[target] = "kept: the corrected normal matrix is not positive definite"
            continue
        params[list(mapping)] = np.linalg.solve(corrected, cross)[: len(mapping)]
        report[target] = "refitted"
    refit = dataclasses.replace(equations, params=tuple(float(x) for x in params))
    return refit, report


def refit_joint(
    de: Equations,
    ae: Equations,
    datasets: Sequence[Dataset],
    estimates: Sequence[StateEstimate] | None = None,
    *,
    max_steps: int = 1000,
) -> tuple[Equations, dict[str, object]]:
    """The AE equations' parameters by maximum likelihood with the states unknown.

    The model: the states follow the DE equations (process noise as
    :class:`jaxdmd.estimate.ModelSmoother` chooses it) and are measured with white noise (its
    variance estimated as in :func:`smoothed_states`); every algebraic variable is measured
    without noise and equals its AE equation up to an error of unknown variance. The Kalman
    filter with the AE equations as measurement equations gives the likelihood of the data
    (its innovations), a differentiable function of the AE parameters and error variances,
    maximised by BFGS (optimistix) from the given parameters. This is the errors-in-variables
    estimate that uses every channel: the noisy states, their dynamics, and the clean algebraic
    measurements, which pin the states down where the equations hold. ``estimates`` are
    :func:`model_states` of the same ``datasets`` if the caller has them (their noise variances,
    process noise and states are reused; else they are computed). Kept if it fails or does not
    raise the likelihood. Returns the equations and a report.
    """
    import optimistix as optx

    from jaxdmd.estimate import ModelSmoother

    if estimates is None or not estimates[0].from_model:
        estimates = model_states(de, datasets)
    states = tuple(de.contract.targets)
    contract = ae.contract
    skeleton = ae.skeleton()
    smoother = ModelSmoother(
        de.skeleton(), de.params, states, datasets, [e.noise for e in estimates],
        ae=skeleton, targets=contract.targets, process=estimates[0].process,
    )  # fmt: skip
    start = np.asarray(ae.params, dtype=float)
    # start the error variances at the equations' residual on the model-smoothed states, and
    # keep them above 1e-10 of the target's variance: an equation that holds exactly would
    # otherwise drive its variance to zero, and the problem's conditioning with it
    observed, predicted = [], []
    for e in estimates:
        data = {n: jnp.asarray(e.dataset[n]) for n in e.dataset.names}
        predicted.append(np.asarray(skeleton(data, jnp.asarray(start))))
        observed.append(np.stack([np.asarray(e.dataset[y]) for y in contract.targets]))
    observed = np.concatenate(observed, axis=1)  # [targets, samples]
    floor = 1e-10 * np.var(observed, axis=1) + 1e-300
    var0 = np.maximum(np.var(observed - np.concatenate(predicted, axis=1), axis=1), 2 * floor)

    n_p = start.size

    def unpack(theta: jax.Array) -> tuple[jax.Array, jax.Array]:
        """parameters and error variances from theta = (p, log(variance - floor))"""
        return theta[:n_p], jnp.asarray(floor) + jnp.exp(theta[n_p:])

    def nll(theta: jax.Array) -> jax.Array:
        return -smoother.log_likelihood(*unpack(theta))

    theta0 = jnp.asarray(np.concatenate([start, np.log(var0 - floor)]))
    before = float(nll(theta0))
    solution = optx.minimise(
        lambda theta, _: nll(theta), optx.BFGS(rtol=1e-8, atol=1e-8), theta0,
        max_steps=max_steps, throw=False,
    )  # fmt: skip
    theta = solution.value
    params, fitted = (np.asarray(x) for x in unpack(theta))
    after = float(nll(theta))
    steps = int(solution.stats["num_steps"])
    report: dict[str, object] = {"steps": steps, "nll_before": before, "nll_after": after}
    if not (np.all(np.isfinite(params)) and np.isfinite(after) and after < before):
        report["kept"] = "the fit failed or did not raise the likelihood"
        return ae, report
    report["error_variance"] = dict(zip(contract.targets, fitted.tolist(), strict=True))
    report["converged"] = steps < max_steps
    return dataclasses.replace(ae, params=tuple(float(x) for x in params)), report


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
        data = json.loads(Path(checkpoint).read_text())
        return search.state_from_dict(data, problem, config)
    return search.init(problem, contract, key, config)


@dataclass(frozen=True)
class Discovery:
    """The discovered differential-algebraic model and the two loops' final states."""

    de: Equations
    ae: Equations | None
    de_state: SearchState
    ae_state: SearchState | None

    def module_source(self) -> str:
        """The model as a Python module: skeletons and their fitted parameters."""
        parts = [
            '"""Model discovered by jaxdmd: state equations (DE) and algebraic equations (AE)."""',
            "",
            "import jax.numpy as jnp  # noqa: F401  (the skeletons may call jnp functions)",
            "",
            self.de.source.rstrip(),
            "",
            f"DE_PARAMS = {list(self.de.params)!r}",
            f"DE_TARGETS = {list(self.de.contract.targets)!r}",
        ]
        if self.ae is not None:
            parts += [
                "",
                self.ae.source.rstrip(),
                "",
                f"AE_PARAMS = {list(self.ae.params)!r}",
                f"AE_TARGETS = {list(self.ae.contract.targets)!r}",
            ]
        return "\n".join(parts) + "\n"
