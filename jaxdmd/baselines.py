"""The paper's SINDy baselines (pysindy), fitted and rolled out like jaxdmd's models.

Three variants (the paper's Table I), all with the Dataset's state-derivative estimates as
``x_dot`` (the same targets jaxdmd fits) and the measured (noisy) states as regressors:

- ``"accurate"``: `pysindy.PolynomialLibrary` of degree 1 (with bias) over the states and the
  controls ``u = (i_d, i_q, P_e, P_m, v_f)``;
- ``"overcomplete"``: the same variables, degree 2;
- ``"missing"``: degree 1 without ``i_d`` and ``i_q``.

Sparsity threshold (STLSQ), chosen on the training data only. With two or more recordings the
training set is split into a fit part and a validation part (the last recording); every
threshold of a grid is fitted on the fit part and scored by the validation error of the
*derivative fit* (the mean over states of MSE / variance of the validation derivatives). With a
single recording, whose last part has usually settled (its derivatives are noise, so the empty
model would win by construction), the threshold is chosen by cross-validation over held-out time
blocks: the recording is cut into ``round(1 / holdout)`` blocks of equal duration, each block is
predicted by the model fitted on the others, and the error is that of the pooled held-out
predictions over the whole recording (MSE / variance per state, mean over states). Either way
the largest threshold within 1 % of the best error wins (the sparsest among the equally good),
and the model is refitted on the whole training set with it. The thresholds are dimensionless:
each target column is divided by its norm and pysindy normalises the library columns
(``normalize_columns=True``), so a threshold is the smallest kept contribution of a unit-norm
term to a unit-norm target; coefficients are scaled back afterwards. `sindy_baseline` takes
only training data, so the test recording cannot leak into the choice.

Rollout: the fitted model is converted to a JAX vector field (coefficients times the polynomial
features, `Block`) and simulated by `jaxdmd.rollout.rollout` in ``mode="de"``: the controls are
played in from the test recording (SINDy has no algebraic loop), the initial state is the
measured one, and the integrator, play-in and metrics are exactly those used for jaxdmd's models.
`Baseline.simulate_pysindy` runs pysindy's own ``simulate`` (RK45) for cross-checking.
"""

from __future__ import annotations

import itertools
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import jax.numpy as jnp
import numpy as np

from jaxdmd.data import Dataset
from jaxdmd.rollout import Block, RolloutConfig, RolloutResult, rollout

__all__ = ["CONTROLS", "DEGREES", "KINDS", "Baseline", "choose_threshold", "sindy_baseline"]

Kind = Literal["accurate", "overcomplete", "missing"]
KINDS: tuple[str, ...] = ("accurate", "overcomplete", "missing")
CONTROLS: dict[str, tuple[str, ...]] = {
    "accurate": ("i_d", "i_q", "P_e", "P_m", "v_f"),
    "overcomplete": ("i_d", "i_q", "P_e", "P_m", "v_f"),
    "missing": ("P_e", "P_m", "v_f"),
}
DEGREES: dict[str, int] = {"accurate": 1, "overcomplete": 2, "missing": 1}
DEFAULT_THRESHOLDS: tuple[float, ...] = (0.0, *np.logspace(-4, 0, 17).tolist())


def _features(z: Any, powers: Any, xp: Any = np) -> Any:
    """Polynomial features ``prod_k z_k ** powers[f, k]``: z [..., n_in] -> [..., n_features]."""
    return xp.prod(z[..., None, :] ** powers, axis=-1)


def _arrays(
    data: Sequence[Dataset], states: Sequence[str], controls: Sequence[str]
) -> tuple[list[np.ndarray], list[np.ndarray], list[np.ndarray], list[np.ndarray]]:
    xs, us, dxs, ts = [], [], [], []
    for ds in data:
        xs.append(np.stack([np.asarray(ds[s]) for s in states], axis=1))
        us.append(np.stack([np.asarray(ds[c]) for c in controls], axis=1))
        dxs.append(np.stack([np.asarray(ds.derivative(s)) for s in states], axis=1))
        ts.append(np.asarray(ds.t))
    return xs, us, dxs, ts


def _fit(
    xs: list[np.ndarray],
    us: list[np.ndarray],
    dxs: list[np.ndarray],
    ts: list[np.ndarray],
    names: Sequence[str],
    degree: int,
    threshold: float,
    alpha: float,
) -> tuple[Any, np.ndarray, np.ndarray]:
    """Fit pysindy on unit-norm targets; returns (model, coefficients [s, F], powers [F, n_in])."""
    import pysindy as ps

    norm = np.sqrt(sum(np.sum(d**2, axis=0) for d in dxs))
    norm = np.where(norm > 0, norm, 1.0)
    model = ps.SINDy(
        optimizer=ps.STLSQ(threshold=threshold, alpha=alpha, normalize_columns=True),
        feature_library=ps.PolynomialLibrary(degree=degree, include_bias=True),
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model.fit(xs, t=ts, x_dot=[d / norm for d in dxs], u=us, feature_names=list(names))
    model.optimizer.coef_ = model.optimizer.coef_ * norm[:, None]  # back to physical units
    coef = np.asarray(model.coefficients(), dtype=np.float64)
    powers = np.asarray(model.feature_library.powers_, dtype=np.int64)
    return model, coef, powers


def _split(train: Sequence[Dataset]) -> tuple[list[Dataset], list[Dataset]]:
    """Fit part and validation part of two or more training recordings: all but the last, and
    the last."""
    return list(train[:-1]), [train[-1]]


def _block_errors(
    ds: Dataset,
    states: Sequence[str],
    controls: Sequence[str],
    degree: int,
    thresholds: Sequence[float],
    holdout: float,
    alpha: float,
) -> list[tuple[float, float]]:
    """(threshold, held-out error) by cross-validation over time blocks of one recording.

    The recording is cut into ``k = max(2, round(1 / holdout))`` blocks of equal duration; for
    every threshold and block the model is fitted on the other blocks (the pieces before and
    after it, as separate trajectories) and predicts the held-out block's derivatives. The error
    is the mean over states of MSE / variance of the pooled held-out predictions over the whole
    recording, so the transients count wherever they are.
    """
    (x,), (u,), (dx,), (t,) = _arrays([ds], states, controls)
    n = t.shape[0]
    k = max(2, round(1.0 / holdout))
    cuts = t[0] + (t[-1] - t[0]) * np.arange(1, k) / k
    edges = [0, *np.searchsorted(t, cuts).tolist(), n]
    blocks = [(a, b) for a, b in itertools.pairwise(edges) if b > a]
    names = (*states, *controls)
    z = np.concatenate([x, u], axis=1)
    var = np.maximum(np.var(dx, axis=0), 1e-300)
    table = []
    for th in thresholds:
        pred = np.empty_like(dx)
        for a, b in blocks:
            pieces = [(0, a), (b, n)]
            pieces = [(i, j) for i, j in pieces if j - i >= 2]
            xs = [x[i:j] for i, j in pieces]
            us = [u[i:j] for i, j in pieces]
            dxs = [dx[i:j] for i, j in pieces]
            ts = [t[i:j] for i, j in pieces]
            _, coef, powers = _fit(xs, us, dxs, ts, names, degree, float(th), alpha)
            pred[a:b] = _features(z[a:b], powers) @ coef.T
        err = float(np.mean(np.mean((pred - dx) ** 2, axis=0) / var))
        table.append((float(th), err if np.isfinite(err) else float("inf")))
    return table


def choose_threshold(
    train: Sequence[Dataset],
    states: Sequence[str],
    controls: Sequence[str],
    degree: int,
    *,
    thresholds: Sequence[float] = DEFAULT_THRESHOLDS,
    holdout: float = 0.25,
    alpha: float = 0.05,
    tolerance: float = 0.01,
) -> tuple[float, tuple[tuple[float, float], ...]]:
    """The STLSQ threshold with the best validation derivative error, from training data only.

    Returns ``(threshold, table)`` with ``table`` the (threshold, validation error) pairs; the
    error is the mean over states of MSE(predicted - estimated derivative) / variance of the
    estimated derivative on the validation part: the last recording when there are two or more,
    else the held-out time blocks of the single recording (`_block_errors`, ``holdout`` the
    share of one block). Among thresholds within ``tolerance`` (relative) of the lowest error
    the largest is chosen.
    """
    if len(train) == 1:
        table = _block_errors(train[0], states, controls, degree, thresholds, holdout, alpha)
        best = min(e for _, e in table)
        chosen = max(th for th, e in table if e <= best * (1.0 + tolerance))
        return chosen, tuple(table)
    fit_part, val_part = _split(train)
    names = (*states, *controls)
    xs, us, dxs, ts = _arrays(fit_part, states, controls)
    vx, vu, vdx, _ = _arrays(val_part, states, controls)
    z_val = np.concatenate([np.concatenate([a, b], axis=1) for a, b in zip(vx, vu, strict=True)])
    d_val = np.concatenate(vdx)
    var = np.maximum(np.var(d_val, axis=0), 1e-300)
    table = []
    for th in thresholds:
        _, coef, powers = _fit(xs, us, dxs, ts, names, degree, float(th), alpha)
        pred = _features(z_val, powers) @ coef.T
        err = float(np.mean(np.mean((pred - d_val) ** 2, axis=0) / var))
        table.append((float(th), err if np.isfinite(err) else float("inf")))
    best = min(e for _, e in table)
    chosen = max(th for th, e in table if e <= best * (1.0 + tolerance))
    return chosen, tuple(table)


@dataclass(frozen=True)
class Baseline:
    """A fitted SINDy baseline: ``d states/dt = coefficients @ features(states, controls)``.

    Attributes:
        kind: ``"accurate"``, ``"overcomplete"`` or ``"missing"``.
        states, controls: the variable names (controls are played in at rollout).
        degree: polynomial degree of the library.
        threshold: the STLSQ threshold chosen on the training data.
        coefficients: [n_states, n_features] in physical units.
        powers: [n_features, n_states + n_controls] exponents of the features.
        feature_names: pysindy's names of the features.
        validation: (threshold, validation error) of every threshold tried.
        model: the fitted `pysindy.SINDy` (for its own ``simulate``/``print``).
    """

    kind: str
    states: tuple[str, ...]
    controls: tuple[str, ...]
    degree: int
    threshold: float
    coefficients: np.ndarray = field(repr=False)
    powers: np.ndarray = field(repr=False)
    feature_names: tuple[str, ...] = field(repr=False)
    validation: tuple[tuple[float, float], ...] = field(repr=False)
    model: Any = field(repr=False, compare=False)

    @property
    def n_terms(self) -> int:
        """The number of nonzero coefficients."""
        return int(np.count_nonzero(self.coefficients))

    def block(self) -> Block:
        """The model as a `jaxdmd.rollout.Block` (JAX vector field over states and controls)."""
        powers = jnp.asarray(self.powers)
        n_s, n_f = self.coefficients.shape

        def fn(*args: Any) -> tuple[Any, ...]:
            *z, p = args
            zz = jnp.stack(jnp.broadcast_arrays(*z), axis=-1)
            theta = _features(zz, powers.astype(zz.dtype), jnp)
            out = theta @ p.reshape(n_s, n_f).T
            return tuple(out[..., j] for j in range(n_s))

        key = f"sindy:{self.powers.tobytes().hex()}:{self.states}:{self.controls}"
        return Block(
            targets=self.states,
            arguments=(*self.states, *self.controls),
            fn=fn,
            params=self.coefficients.ravel(),
            key=key,
        )

    def rollout(self, test: Dataset, config: RolloutConfig | None = None) -> RolloutResult:
        """Simulate on ``test`` from its measured initial state, controls played in."""
        return rollout(self.block(), test, mode="de", config=config)

    def equations(self, precision: int = 4) -> dict[str, str]:
        """Readable equations: ``{"d<state>/dt": "c1 term1 + c2 term2 ..."}``."""
        out = {}
        for i, s in enumerate(self.states):
            terms = [
                f"{c:+.{precision}g}" + ("" if f == "1" else f" {f}")
                for c, f in zip(self.coefficients[i], self.feature_names, strict=True)
                if c != 0
            ]
            out[f"d{s}/dt"] = " ".join(terms) if terms else "0"
        return out

    def simulate_pysindy(self, test: Dataset) -> np.ndarray:
        """pysindy's own simulation (RK45, rtol = atol = 1e-8) with the controls interpolated
        linearly from ``test`` (a callable u): states [n, n_states], for cross-checking."""
        t = np.asarray(test.t)
        u_meas = np.stack([np.asarray(test[c]) for c in self.controls], axis=1)

        def u(s: float) -> np.ndarray:
            return np.array([np.interp(s, t, u_meas[:, j]) for j in range(u_meas.shape[1])])

        x0 = np.array([float(test[s][0]) for s in self.states])
        kws = {"method": "RK45", "rtol": 1e-8, "atol": 1e-8}
        return np.asarray(self.model.simulate(x0, t, u=u, integrator_kws=kws))


def sindy_baseline(
    train: Sequence[Dataset],
    kind: Kind,
    *,
    states: Sequence[str] | None = None,
    controls: Sequence[str] | None = None,
    thresholds: Sequence[float] = DEFAULT_THRESHOLDS,
    holdout: float = 0.25,
    alpha: float = 0.05,
) -> Baseline:
    """Fit one of the paper's SINDy baselines on training recordings only.

    Args:
        train: training recordings (noisy states, derivative estimates in ``derivatives``).
        kind: ``"accurate"`` (degree 1, controls i_d, i_q, P_e, P_m, v_f), ``"overcomplete"``
            (degree 2) or ``"missing"`` (degree 1 without i_d, i_q).
        states: the states to model (default: the first recording's states).
        controls: override the kind's controls (e.g. for other data).
        thresholds: the STLSQ threshold grid (dimensionless; see the module docstring).
        holdout: with a single training recording, the share of one held-out time block of
            the cross-validation (``round(1 / holdout)`` blocks).
        alpha: STLSQ's ridge penalty (only selects the support: pysindy refits it unbiased).

    Returns:
        The fitted `Baseline`; the threshold is chosen by `choose_threshold` on ``train``.
    """
    if kind not in KINDS:
        raise ValueError(f"unknown baseline kind {kind!r}; use one of {KINDS}")
    if not train:
        raise ValueError("sindy_baseline needs at least one training recording")
    states = tuple(states or train[0].state_names)
    controls = tuple(CONTROLS[kind] if controls is None else controls)
    degree = DEGREES[kind]
    missing = [n for n in (*states, *controls) for ds in train if n not in ds]
    if missing:
        raise ValueError(f"the training data lack {sorted(set(missing))}")
    threshold, table = choose_threshold(
        train, states, controls, degree, thresholds=thresholds, holdout=holdout, alpha=alpha
    )
    xs, us, dxs, ts = _arrays(train, states, controls)
    model, coef, powers = _fit(xs, us, dxs, ts, (*states, *controls), degree, threshold, alpha)
    return Baseline(
        kind=kind,
        states=states,
        controls=controls,
        degree=degree,
        threshold=threshold,
        coefficients=coef,
        powers=powers,
        feature_names=tuple(model.get_feature_names()),
        validation=table,
        model=model,
    )
