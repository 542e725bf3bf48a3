"""Refinement of a loop's result: refits of the parameters and estimates of the states.

The search chooses the structure; these estimators choose the parameters better than the
search's own fit can, and estimate the states the AE loop regresses on:

- :func:`refit_integral`: the state equations refitted in the integral form (no derivatives).
- :func:`smoothed_states`, :func:`model_states`: the noisy states replaced by an estimate (a
  generic smoother, or a Kalman smoother whose process model is the discovered state equations).
- :func:`refit_bias_compensated`: the AE fit corrected for the noise the estimated states keep.
- :func:`refit_joint`: the AE parameters by maximum likelihood with the states unknown.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Collection, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxdmd import lines as ln
from jaxdmd import search, select
from jaxdmd.data import Dataset
from jaxdmd.estimate import StateEstimate, model_smoother, without_covariance
from jaxdmd.fit import FitConfig
from jaxdmd.problems import EstimatorGains, de_problem, estimator_gains
from jaxdmd.search import Equations
from jaxdmd.skeleton import SkeletonError


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
    equations: Equations,
    estimates: Sequence[StateEstimate],
    weights: np.ndarray | None = None,
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
    parameters; a line built from products of the others (:func:`jaxdmd.select.linked`) keeps
    its coefficients and is built again from those lines as refitted. ``weights``
    (``[targets, N]``, the recordings concatenated in the order of ``estimates``) weight the
    samples (:func:`jaxdmd.select.weighted_by_recording`); default 1. Returns the equations
    and, per target, what was done.
    """

    if any(e.covariance is None for e in estimates):
        raise ValueError(
            "the bias compensation needs the states' covariances; these estimates have none "
            "(estimate.without_covariance)"
        )
    given, link = equations, select.linked(equations)
    if link is not None:  # a line built from the others moves with them
        equations = link.equations
    lines, mappings = ln.split_lines(equations.source)
    params = np.array(equations.params, dtype=float)
    contract = equations.contract
    report: dict[str, str] = {}
    sizes = [len(np.asarray(e.dataset.t)) for e in estimates]
    starts = np.cumsum([0, *sizes[:-1]])
    for j, (target, line, mapping) in enumerate(
        zip(contract.targets, lines, mappings, strict=True)
    ):
        skeleton = search._line_skeleton(contract, line)
        names = tuple(skeleton.arguments)
        if not names:
            report[target] = "kept: a constant has no regressors"
            continue
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
        for estimate, start, size in zip(estimates, starts, sizes, strict=True):
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
            cov = np.asarray(estimate.covariance)[:, rows][:, :, rows]  # [n, A, A]
            y = np.asarray(ds[target], dtype=float) - offset
            if weights is None:
                gram = gram + g.T @ g
                cross = cross + g.T @ y
                correction = correction + np.einsum("npa,nab,nqb->pq", jac, cov, jac)
            else:
                w = np.asarray(weights[j][start : start + size], dtype=float)
                gram = gram + g.T @ (w[:, None] * g)
                cross = cross + g.T @ (w * y)
                correction = correction + np.einsum("n,npa,nab,nqb->pq", w, jac, cov, jac)
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
    if link is None:
        return refit, report
    back = link.back(refit)
    if back is None:
        return given, dict.fromkeys(report, f"kept: {UNLINKED}")
    return back, report


# why a refit is not kept where a line built from the others cannot be written back with the
# refitted lines in it (:meth:`jaxdmd.select.Linked.back`)
UNLINKED = "the line built from the others exceeds a skeleton's size once refitted"


# An algebraic equation holds when, fitted with the states unknown, its error keeps less than this
# share of its variable's standard deviation. The algebraic channels are exact functions of the
# states, so an equation with the right terms follows its channel almost exactly (1e-5 to 1e-4 of
# the variable's deviation in the default runs of seeds 0-2; 1e-5 is the fit's floor, the error
# variance being kept above 1e-10 of the variable's); one that misses a term or holds a stand-in
# for it cannot (4e-3 to 1e-1 there).
# A finding for the report: it changes no equation.
HOLDS = 1e-3


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
    process noise and states are reused; else they are computed). A line built from products of
    the others (:func:`jaxdmd.select.composed_lines`: a power from the currents and voltages)
    is fitted as the relation it is (:func:`jaxdmd.select.linked`): it moves with the lines it
    reads, and its variable's measurements inform their parameters; it is written back as a
    line in the states with the refitted lines in it (:meth:`jaxdmd.select.Linked.back`). Kept if
    it fails or does not raise the likelihood. Returns the equations and a report.
    """
    import optimistix as optx

    from jaxdmd.estimate import ModelSmoother

    if estimates is None or not estimates[0].from_model:
        estimates = model_states(de, datasets)
    given, link = ae, select.linked(ae)
    if link is not None:  # a line built from the others is fitted as the relation it is
        ae = link.equations
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
    variance = np.var(observed, axis=1)  # of each algebraic variable
    floor = 1e-10 * variance + 1e-300
    var0 = np.maximum(np.var(observed - np.concatenate(predicted, axis=1), axis=1), 2 * floor)

    n_p = start.size

    def unpack(theta: jax.Array) -> tuple[jax.Array, jax.Array]:
        """parameters and error variances from theta = (p, log(variance - floor))"""
        return theta[:n_p], jnp.asarray(floor) + jnp.exp(theta[n_p:])

    # the recordings enter the compiled likelihood as its argument: as constants, every compiled
    # program would hold its own copy of them (a quarter of a GB at 4 x 1e5 samples)
    recordings = smoother.recordings

    def nll(theta: jax.Array, recordings: Any) -> jax.Array:
        return -smoother.log_likelihood(*unpack(theta), recordings)

    theta0 = jnp.asarray(np.concatenate([start, np.log(var0 - floor)]))
    # the likelihood before and after, compiled once: run op by op, each evaluation cost
    # seconds of small compilations (the optimiser compiles its own, from nll)
    evaluate = jax.jit(nll)
    before = float(evaluate(theta0, recordings))
    solution = optx.minimise(
        nll, optx.BFGS(rtol=1e-8, atol=1e-8), theta0, recordings, max_steps=max_steps,
        throw=False,
    )  # fmt: skip
    theta = solution.value
    params, fitted = (np.asarray(x) for x in unpack(theta))
    after = float(evaluate(theta, recordings))
    steps = int(solution.stats["num_steps"])
    report: dict[str, object] = {"steps": steps, "nll_before": before, "nll_after": after}
    if not (np.all(np.isfinite(params)) and np.isfinite(after) and after < before):
        report["kept"] = "the fit failed or did not raise the likelihood"
        return given, report
    report["error_variance"] = dict(zip(contract.targets, fitted.tolist(), strict=True))
    # how well each equation holds: its error's standard deviation as a share of its variable's
    share = np.sqrt(fitted / (variance + 1e-300))
    report["error_share"] = dict(zip(contract.targets, share.tolist(), strict=True))
    report["not_holding"] = [t for t, x in zip(contract.targets, share, strict=True) if x > HOLDS]
    report["converged"] = steps < max_steps
    refitted = dataclasses.replace(ae, params=tuple(float(x) for x in params))
    if link is not None:
        back = link.back(refitted)
        if back is None:
            report["kept"] = UNLINKED
            return given, report
        refitted = back
    return refitted, report


def sharpened_states(
    de: Equations,
    ae: Equations,
    datasets: Sequence[Dataset],
    estimates: Sequence[StateEstimate],
    *,
    max_steps: int = 1000,
) -> tuple[list[StateEstimate] | None, dict[str, Any]]:
    """The states estimated again, from the algebraic measurements too, through the lines of
    ``ae`` that hold with the states unknown.

    The model-smoothed states keep the noise their own measurements leave, and an algebraic
    line passes it on amplified: the terminal voltage's Park components read the rotor angle,
    and a stator current reads them divided by x'_d, so an angle known to 1e-3 rad leaves the
    current's coefficients attenuated by a few percent (errors in variables). The algebraic
    variables are measured without noise, and a line that holds (:func:`refit_joint`: its
    error's standard deviation within :data:`HOLDS` of its variable's) ties them to the states
    exactly: v_d = V sin(delta - theta) pins the angle. So the joint refit of ``ae`` finds the
    lines that hold, and the Kalman smoother of :func:`jaxdmd.estimate.model_states` runs again
    with those lines as measurement equations (their fitted error variances; a line that does
    not hold is left out: a stand-in would pull the states towards its error). ``estimates``
    are ``model_states`` of ``datasets`` (with their covariances); their noise and process-noise
    factors are kept. A line that, alone, moves a state away from its own measurements further
    than the first estimate's uncertainty explains (:data:`DEPARTURE`) holds only because the
    states bend to it, and is left out; the others are used together if together they pass
    the same check, else none is. Returns the new estimates (None where no line is left, the
    refit fails or the lines together move the states away) and a report."""
    from jaxdmd.estimate import ModelSmoother

    try:
        refitted, joint = refit_joint(de, ae, datasets, estimates, max_steps=max_steps)
    except (ValueError, np.linalg.LinAlgError) as err:
        return None, {"kept": f"the joint refit failed: {err}"}
    targets = tuple(ae.contract.targets)
    share = joint.get("error_share")
    if not isinstance(share, dict):
        return None, {"kept": str(joint.get("kept", "the joint refit failed"))}
    holding = [t for t in targets if share[t] <= HOLDS]
    report: dict[str, Any] = {"through": {}}
    if not holding:
        report["kept"] = "no algebraic line holds with the states unknown"
        return None, report
    measured = np.concatenate(
        [np.stack([np.asarray(e.dataset[t], dtype=float) for t in targets]) for e in estimates],
        axis=1,
    )
    smoother = ModelSmoother(
        de.skeleton(), de.params, tuple(de.contract.targets), datasets,
        [e.noise for e in estimates], ae=refitted.skeleton(), targets=targets,
        process=estimates[0].process,
    )  # fmt: skip
    fitted = joint["error_variance"]

    def through(lines: Collection[str]) -> tuple[list[StateEstimate], dict[str, float]]:
        """The states smoothed with ``lines`` as measurements, and their departure (a line
        left out is given an error variance 1e8 times its variable's: it informs nothing)."""
        variance = [
            fitted[t] if t in lines else 1e8 * float(np.var(measured[i]))
            for i, t in enumerate(targets)
        ]  # fmt: skip
        found = smoother.smooth(refitted.params, variance)
        if not all(np.all(np.isfinite(np.asarray(e.dataset.values))) for e in found):
            return found, dict.fromkeys(found[0].states, np.inf)
        return found, _departure(datasets, estimates, found)

    # each line alone first: one that moves a state away from its measurements is left out;
    # then the others together, all or none
    alone = {t: through([t]) for t in holding}
    usable = [t for t in holding if max(alone[t][1].values()) <= DEPARTURE]
    report["left_out"] = {
        t: {"departure": alone[t][1], "error_share": share[t]} for t in holding if t not in usable
    }
    if not usable:
        report["kept"] = _moved(alone[holding[0]][1], "each line that holds")
        return None, report
    sharper, departure = alone[usable[0]] if len(usable) == 1 else through(usable)
    report["departure"] = departure
    if max(departure.values()) > DEPARTURE:
        report["together"] = {t: share[t] for t in usable}
        report["kept"] = _moved(departure, "the lines together")
        return None, report
    report["through"] = {t: share[t] for t in usable}
    return sharper, report


def _moved(departure: dict[str, float], what: str) -> str:
    worst = max(departure, key=departure.__getitem__)
    return (
        f"{what} would move {worst} away from its measurements ({departure[worst]:.3g} of its "
        f"noise variance beyond its uncertainty; at most {DEPARTURE})"
    )


# How far the states estimated again through lines that hold may move from their own
# measurements, beyond what the first estimate's uncertainty explains (:func:`_departure`), as a
# share of each state's noise variance (0.03: a sixth of the noise's standard deviation, over
# every sample). Through lines that are right it is zero give or take its sampling spread
# (about 0.01 at the benchmark's 4,000 samples) and the state equations' own error (which
# makes their smoother a little too sure); a line that holds only because the states bend to
# it (a stand-in whose terms absorb an offset of the angle: V sin(delta - theta) and
# V cos(delta - theta) together rotate it) moves them further. Measured on Table I: where the
# lines were used, at most 0.024 (generator 39 seed 1, e''_d); generator 30 seed 0, where
# v_d, P_e and i_d each shift the angle by 0.016 rad, 0.56 (used, the model simulated the test
# fault 70 times worse). Where each line passes alone but not all together (six pairs; 0.03 to
# 0.73 together), none is used: leaving out the line that moved the states furthest alone
# until the rest pass made three of the six better and three worse, seed 1's mean MAPE 0.052
# -> 0.097 % (generator 30 0.33 -> 0.77 %, with only v_d and v_q).
DEPARTURE = 0.03


def _departure(
    datasets: Sequence[Dataset],
    before: Sequence[StateEstimate],
    after: Sequence[StateEstimate],
) -> dict[str, float]:
    """Per state, how much further the estimates ``after`` lie from the states' measurements in
    ``datasets`` than ``before`` (the model-smoothed estimates, with their covariances), beyond
    what ``before``'s uncertainty explains: (sum (y - x_after)^2 - (y - x_before)^2 - (P_before
    - P_after)) / sigma^2, summed over the recordings' samples and divided by their number. An
    estimate that fitted part of the noise (x_before, posterior variance P_before) lies closer
    to the measurements than the true states by P_before on average; one that finds the true
    states lies at the noise from them."""
    states = before[0].states
    out = {}
    for i, s in enumerate(states):
        excess, n = 0.0, 0
        for ds, b, a in zip(datasets, before, after, strict=True):
            y = np.asarray(ds[s], dtype=float)
            var = max(b.noise[s], 1e-12 * float(np.var(y)) + 1e-300)
            moved = (y - np.asarray(a.dataset[s])) ** 2 - (y - np.asarray(b.dataset[s])) ** 2
            spread = 0.0
            if b.covariance is not None and a.covariance is not None:
                spread = np.asarray(b.covariance[:, i, i]) - np.asarray(a.covariance[:, i, i])
            excess += float(np.sum(moved - spread)) / var
            n += y.size
        out[s] = excess / n
    return out


def _bic_penalty(datasets: Sequence[Dataset], targets: int) -> float:
    """BIC's penalty per parameter, in nats, of a likelihood of ``targets`` algebraic variables
    over every sample of ``datasets`` (:func:`refit_joint`'s)."""
    return float(0.5 * np.log(sum(ds.n_samples for ds in datasets) * targets))


def joint_rating(
    de: Equations,
    ae: Equations,
    datasets: Sequence[Dataset],
    estimates: Sequence[StateEstimate],
    max_steps: int = 1000,
    *,
    progress: Callable[[Any], None] | None = None,
) -> float:
    """The log-likelihood of the algebraic equations ``ae`` with the states unknown, their
    parameters fitted by it (:func:`refit_joint`, from theirs), less BIC's penalty for them;
    -inf if the refit fails. (``progress`` unused: the task signature of
    :mod:`jaxdmd.workers`.)"""
    try:
        _, report = refit_joint(de, ae, datasets, estimates, max_steps=max_steps)
    except (ValueError, np.linalg.LinAlgError):
        return -np.inf
    nll = np.nanmin([report["nll_before"], report["nll_after"]])
    if not np.isfinite(nll):
        return -np.inf
    return float(-nll - _bic_penalty(datasets, len(ae.contract.targets)) * len(ae.params))


def joint_likelihood(
    de: Equations,
    datasets: Sequence[Dataset],
    estimates: Sequence[StateEstimate],
    *,
    max_steps: int = 1000,
    jobs: int = 1,
) -> Callable[[Sequence[Equations]], list[float]]:
    """:func:`joint_rating` of each of several algebraic equation sets: the arbiter
    :func:`jaxdmd.select.select_algebraic` asks where the closed model and the held-out fit
    cannot tell two lines apart. Each rating is a joint refit (10-40 s on the benchmark); with
    ``jobs`` above 1 all but the first run in worker processes beside it (one BLAS thread
    each, as here: the same ratings either way)."""
    from jaxdmd import workers

    # a rating does not read the states' covariances: the workers are sent them without
    args = (datasets, [without_covariance(e) for e in estimates], max_steps)

    def rate(equations: Sequence[Equations]) -> list[float]:
        equations = list(equations)
        ahead = (
            [workers.start(joint_rating, de, ae, *args) for ae in equations[1:]] if jobs > 1 else []
        )
        with workers.one_blas_thread():
            out = [joint_rating(de, ae, *args) for ae in equations[: len(equations) - len(ahead)]]
            for ae, worker in zip(equations[len(out) :], ahead, strict=True):
                try:
                    out.append(float(worker.result()))
                except workers.WorkerError:  # a worker that failed: its rating made here
                    out.append(joint_rating(de, ae, *args))
        return out

    return rate


# The screen before a product's joint refit (:func:`refit_joint_products`): its held-out
# least-squares fit of the variable on the estimated states must be within this factor of the
# line's own. On those states a stand-in fits about as well as the right terms, so the screen
# only spares a joint refit (a minute or more) to products that cannot be the line. Measured on
# generator 31's default runs: the products of the lines that hold fit P_e 0.7 times its line's
# error on seed 0 (the product then won the likelihood by 1,388 nats) and 12 times on seed 1
# (it lost by 5,629 nats).
PRODUCT_SCREEN = 5.0


def refit_joint_products(
    de: Equations,
    fitted: Equations,
    report: dict[str, Any],
    datasets: Sequence[Dataset],
    estimates: Sequence[StateEstimate],
    state: search.SearchState,
    *,
    variables: Collection[str] | None = None,
    max_steps: int = 1000,
) -> tuple[Equations | None, dict[str, Any]]:
    """The algebraic lines that do not hold rebuilt from the lines that do, judged by the joint
    likelihood.

    ``fitted`` and ``report`` are :func:`refit_joint`'s result. A line that does not hold with
    the states unknown (``report["not_holding"]``) misses a term or holds a stand-in for one.
    A power is a product of voltages and currents, and the selection builds such lines from the
    AE loop's own lines (:func:`jaxdmd.select.composed_lines`), stand-ins and all. Here the
    candidate is the best-fitting product of the lines that hold, their jointly fitted
    parameters written in. It is screened by its held-out fit of the variable in ``state`` (the
    AE problem on the estimated states: within :data:`PRODUCT_SCREEN` of the line's own), then
    the whole structure is refitted jointly with it, from ``fitted``'s parameters (the new
    line's from least squares), and kept if its likelihood, less BIC's penalty for its
    parameters, beats the structure's. The lines that do not hold are taken in turn, the worst
    first; once one is rebuilt, the others are tried again (with one more line that holds),
    each candidate once.

    ``variables``: the algebraic variables whose lines may be rebuilt (None: every one).
    Returns the equations with their jointly fitted parameters (None if no candidate was kept)
    and the report of the structure kept (:func:`refit_joint`'s), with every trial under
    ``"products"``.
    """
    contract = fitted.contract
    targets = list(contract.targets)
    penalty = _bic_penalty(datasets, len(targets))
    trials: list[dict[str, Any]] = []
    best_eq: Equations | None = None
    seen: set[tuple[str, str]] = set()  # (variable, line): each candidate judged once
    tried: set[str] = set()  # the variables tried since the structure last changed
    changes = 0
    while changes < len(targets):
        suspects = [
            t for t in report.get("not_holding", [])
            if t not in tried and (variables is None or t in variables)
        ]  # fmt: skip
        if not suspects:
            break
        target = max(suspects, key=lambda t: report["error_share"][t])
        tried.add(target)
        j = targets.index(target)
        holding = [k for k, t in enumerate(targets) if t not in report["not_holding"]]
        if len(holding) < 2:  # a product of one line with itself is no voltage times a current
            continue
        composed = select.composed_lines(state, j, fitted, holding)
        if not composed:
            continue
        lines, maps = ln.split_lines(fitted.source)
        losses = search.cross_validated_losses(state, j, [ln.renumbered(lines[j]), *composed])
        best = int(np.argmin(losses[1:]))
        line, loss = composed[best], float(losses[1 + best])
        if (target, line.text) in seen:
            continue
        seen.add((target, line.text))
        trial: dict[str, Any] = {
            "target": target, "line": line.text, "held_out_nmse": loss,
            "line_held_out_nmse": float(losses[0]),
        }  # fmt: skip
        trials.append(trial)
        if not loss <= PRODUCT_SCREEN * losses[0]:
            trial["kept"] = f"screened out: held-out fit above {PRODUCT_SCREEN:g} x the line's"
            continue
        start = _with_line(fitted, lines, maps, j, line, state)
        if start is None:
            trial["kept"] = "does not fit or does not compile"
            continue
        refitted, joint = refit_joint(de, start, datasets, estimates, max_steps=max_steps)
        trial.update(steps=joint["steps"], nll_after=joint["nll_after"])
        if "kept" in joint:
            trial["kept"] = joint["kept"]
            continue
        gain = report["nll_after"] - joint["nll_after"]
        trial["gain"] = float(gain - penalty * (len(refitted.params) - len(fitted.params)))
        if trial["gain"] <= 0:  # nats, BIC's penalty included
            trial["kept"] = "the likelihood less BIC's penalty is not higher"
            continue
        trial["chosen"] = True
        first = report.get("structure_before", report)
        report = dict(joint, structure_before={k: first[k] for k in _FIRST if k in first})
        fitted = best_eq = refitted
        tried, changes = set(), changes + 1  # with one more line that holds, others may be
    report = dict(report)
    if trials:
        report["products"] = trials
    return best_eq, report


# what a report keeps of the structure before a product replaced a line
_FIRST = ("nll_before", "nll_after", "steps", "error_share", "not_holding", "simulation_nrmse")


def _with_line(
    fitted: Equations, lines: Sequence[ln.Line], maps: Sequence[Sequence[int]], j: int,
    line: ln.Line, state: search.SearchState,
) -> Equations | None:  # fmt: skip
    """``fitted`` with line ``j`` replaced by ``line``, whose parameters are fitted by least
    squares on ``state``'s problem; the other lines keep theirs. None if the line does not fit or
    the equations do not compile (over the budget of a skeleton)."""
    compiled = search.compiled_lines(state.contract, [line])
    if not compiled:
        return None
    skeleton = compiled[0][1]
    n = state.problem.targets.shape[1]
    ((_, (result,)),) = search.fold_fits(state, j, [skeleton], np.zeros(n, dtype=int))
    if result.error is not None:
        return None
    new = list(lines)
    new[j] = line
    params: list[float] = []
    for k, mapping in enumerate(maps):
        if k == j:
            params += [float(x) for x in np.asarray(result.params)[: line.n_params]]
        else:
            params += [fitted.params[i] for i in mapping]
    losses = list(fitted.losses)
    losses[j] = float(np.asarray(result.losses)[0])
    contract = fitted.contract
    source = ln.assemble(contract.function_name, contract.arguments, new, contract.outputs)
    try:
        skeleton = search._compile(source, contract)
    except SkeletonError:  # over the skeleton's budget (a long composed line)
        return None
    return dataclasses.replace(
        fitted, source=skeleton.source, params=tuple(params), losses=tuple(losses)
    )
