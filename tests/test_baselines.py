"""Tests of jaxdmd.baselines: SINDy baselines on data from a known linear system."""

from __future__ import annotations

import inspect
import itertools

import jax
import numpy as np
import pytest
from scipy.integrate import solve_ivp

import jaxdmd  # noqa: F401  (float64)
from jaxdmd.baselines import CONTROLS, sindy_baseline
from jaxdmd.data import Dataset
from jaxdmd.rollout import metrics

STATES = ("x1", "x2")
CTRL = CONTROLS["accurate"]  # i_d, i_q, P_e, P_m, v_f
A = np.array([[-1.0, 2.0], [-2.0, -0.5]])
B = np.array([[0.0, 1.5, 0.0, 0.5, 0.0], [1.0, 0.0, -0.8, 0.0, 0.3]])
C = np.array([0.2, -0.1])


def _recording(seed: int, events: tuple[float, ...] = (1.0, 1.1), t_end: float = 4.0) -> Dataset:
    """dx/dt = A x + B u + c with smooth random controls that jump at the events."""
    rng = np.random.default_rng(seed)
    f = rng.uniform(0.3, 2.0, size=5)
    ph = rng.uniform(0, 2 * np.pi, size=5)
    amp = rng.uniform(0.5, 1.5, size=5)
    jump = rng.normal(size=(len(events), 5))

    def u(s: float) -> np.ndarray:
        v = amp * np.sin(2 * np.pi * f * s + ph)
        for k, e in enumerate(events):
            if s >= e:
                v = v + jump[k]
        return v

    def rhs(s, x):
        return A @ x + B @ u(s) + C

    t = np.round(np.arange(0.0, t_end + 1e-9, 0.01), 10)
    cuts, xs, x0 = [0.0, *events, t_end], [], rng.normal(size=2)
    for a, b in itertools.pairwise(cuts):
        sel = (t >= a) & ((t < b) if b < t_end else (t <= b))
        sol = solve_ivp(rhs, (a, b), x0, rtol=1e-11, atol=1e-11, dense_output=True)
        xs.append(sol.sol(t[sel]).T)
        x0 = sol.y[:, -1]
    x = np.concatenate(xs)
    U = np.array([u(s) for s in t])
    dx = np.array([rhs(s, xi) for s, xi in zip(t, x, strict=True)])
    channels = {"x1": x[:, 0], "x2": x[:, 1]} | {c: U[:, j] for j, c in enumerate(CTRL)}
    roles = {"x1": "state", "x2": "state"} | {c: "input" for c in CTRL}
    return Dataset.create(
        t,
        channels,
        roles,
        derivatives={"x1": dx[:, 0], "x2": dx[:, 1]},
        events=events,
        label=f"seed {seed}",
    )


@pytest.fixture(scope="module")
def data() -> tuple[list[Dataset], Dataset]:
    return [_recording(1), _recording(2), _recording(3)], _recording(4)


def test_accurate_priors_recover_a_linear_system(data) -> None:
    train, test = data
    base = sindy_baseline(train, "accurate")
    assert base.states == STATES and base.controls == CTRL
    truth = np.concatenate([C[:, None], A, B], axis=1)  # features 1, x1, x2, u...
    assert base.feature_names[:3] == ("1", "x1", "x2")
    np.testing.assert_allclose(base.coefficients, truth, atol=1e-6)
    assert base.n_terms == np.count_nonzero(truth)  # the threshold pruned the zero terms
    res = base.rollout(test)
    assert not res.diverged
    assert metrics(res, test)["mean"]["r2"] > 0.9999
    eqs = base.equations()
    assert set(eqs) == {"dx1/dt", "dx2/dt"} and "i_q" in eqs["dx1/dt"]


def test_missing_variables_score_worse(data) -> None:
    train, test = data
    good = metrics(sindy_baseline(train, "accurate").rollout(test), test)["mean"]["r2"]
    base = sindy_baseline(train, "missing")
    assert base.controls == ("P_e", "P_m", "v_f")
    bad = metrics(base.rollout(test), test)["mean"]["r2"]
    assert bad < good - 0.01


def test_overcomplete_library_and_pysindy_agree(data) -> None:
    train, _ = data
    over = sindy_baseline(train[:1], "overcomplete", thresholds=(0.0, 1e-3, 1e-2))
    assert over.degree == 2 and len(over.feature_names) == 36  # C(7 + 2, 2)
    assert over.coefficients.shape == (2, 36)
    # jaxdmd's diffrax rollout of the converted model equals pysindy's own simulate
    base = sindy_baseline(train[:1], "accurate", thresholds=(0.0, 1e-2))
    smooth = _recording(5, events=(), t_end=1.0)
    ours = base.rollout(smooth)
    theirs = base.simulate_pysindy(smooth)
    assert not ours.diverged
    for j, s in enumerate(base.states):
        np.testing.assert_allclose(ours[s], theirs[:, j], atol=1e-5)


def test_threshold_is_chosen_on_training_data_only(data) -> None:
    params = inspect.signature(sindy_baseline).parameters
    assert "test" not in params and list(params)[:2] == ["train", "kind"]
    train, _ = data
    base = sindy_baseline(train, "accurate")
    assert base.threshold in [th for th, _ in base.validation]
    best = min(e for _, e in base.validation)
    assert dict(base.validation)[base.threshold] <= 1.01 * best
    with pytest.raises(ValueError, match="kind"):
        sindy_baseline(train, "bogus")  # type: ignore[arg-type]


def _settling_recording(seed: int, t_end: float = 10.0) -> Dataset:
    """dx/dt = A x + B u + c with controls whose oscillation dies out (over 1.5 s) and that
    jump at a fault (1.0 s) and its clearing (1.1 s): the last quarter has settled, so its
    derivative estimates are noise. States with 1 % noise, derivatives estimated."""
    events = (1.0, 1.1)
    rng = np.random.default_rng(seed)
    f = rng.uniform(0.3, 2.0, size=5)
    ph = rng.uniform(0, 2 * np.pi, size=5)
    amp = rng.uniform(0.5, 1.5, size=5)
    jump = rng.normal(size=(len(events), 5))

    def u(s: float) -> np.ndarray:
        v = amp * np.sin(2 * np.pi * f * s + ph) * np.exp(-s / 1.5)
        for k, e in enumerate(events):
            if s >= e:
                v = v + jump[k]
        return v

    def rhs(s, x):
        return A @ x + B @ u(s) + C

    t = np.round(np.arange(0.0, t_end + 1e-9, 0.01), 10)
    cuts, xs, x0 = [0.0, *events, t_end], [], rng.normal(size=2)
    for a, b in itertools.pairwise(cuts):
        sel = (t >= a) & ((t < b) if b < t_end else (t <= b))
        sol = solve_ivp(rhs, (a, b), x0, rtol=1e-11, atol=1e-11, dense_output=True)
        xs.append(sol.sol(t[sel]).T)
        x0 = sol.y[:, -1]
    x = np.concatenate(xs)
    U = np.array([u(s) for s in t])
    channels = {"x1": x[:, 0], "x2": x[:, 1]} | {c: U[:, j] for j, c in enumerate(CTRL)}
    roles = {"x1": "state", "x2": "state"} | {c: "input" for c in CTRL}
    ds = Dataset.create(t, channels, roles, events=events)
    return ds.with_noise(jax.random.key(seed), level=0.01)


def test_one_training_recording_gives_a_non_empty_model() -> None:
    """With one recording the threshold is chosen on held-out time blocks over the whole record,
    not on its settled last quarter (where the empty model would win by construction)."""
    ds = _settling_recording(1)
    base = sindy_baseline([ds], "accurate")
    assert base.n_terms >= 4, base.equations()
    assert dict(base.validation)[base.threshold] < 0.5  # held-out error / variance
    coef = dict(zip(base.feature_names, base.coefficients[0], strict=True))
    np.testing.assert_allclose([coef["x1"], coef["x2"]], A[0], rtol=0.1)
    coef = dict(zip(base.feature_names, base.coefficients[1], strict=True))
    np.testing.assert_allclose([coef["x1"], coef["x2"]], A[1], rtol=0.1)
