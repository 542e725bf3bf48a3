"""Tests of jaxdmd.rollout: play-in across jumps, the true model reproduces its data, divergence,
metrics on hand-computed values."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from scipy.integrate import solve_ivp

import jaxdmd  # noqa: F401  (float64)
from jaxdmd.data import Dataset
from jaxdmd.prompts import Contract, Variable
from jaxdmd.rollout import (
    Block,
    at_equilibrium,
    fault_window,
    interpolate,
    metrics,
    play_in_knots,
    rollout,
    score,
)
from jaxdmd.search import Equations

OMEGA_B = 2 * math.pi * 60
M, D, PMAX = 10.0, 2.0, 2.0
EVENTS = (1.0, 1.1)


def _equations(loop: str, targets, states, library, source, params) -> Equations:
    contract = Contract(
        loop=loop,
        targets=tuple(targets),
        states=tuple(Variable(s, "state") for s in states),
        library=tuple(Variable(n, r) for n, r in library),
    )
    return Equations(contract, source, tuple(params), (0.0,) * len(targets), 0.0)


# ---------------------------------------------------------------------------- play-in


def _ramp_data(event: float) -> Dataset:
    """x' = u with u = t before the event and 2 + t/2 after it (a jump), x(0) = 0."""
    t = np.round(np.arange(0.0, 3.0 + 1e-9, 0.01), 10)
    u = np.where(t < event, t, 2.0 + 0.5 * t)
    x = np.where(t < event, t**2 / 2, event**2 / 2 + 2 * (t - event) + 0.25 * (t**2 - event**2))
    return Dataset.create(
        t, {"x": x, "u": u}, {"x": "state", "u": "input"}, derivatives={"x": u}, events=(event,)
    )


RAMP = _equations(
    "DE", ["x"], ["x"], [("u", "input")], "def f(x, u, p):\n    return p[0] * u\n", [1.0]
)


@pytest.mark.parametrize("event", [1.0, 1.005])
def test_play_in_across_a_jump_is_exact(event: float) -> None:
    ds = _ramp_data(event)
    res = rollout(RAMP, ds, mode="de")
    assert res.status == "ok" and not res.diverged
    assert res.played_in == ("u",)
    np.testing.assert_allclose(res["x"], ds["x"], atol=1e-9)


def test_wrapped_angle_is_played_in_as_a_continuous_signal() -> None:
    """x' = cos(theta) with theta = 3 t recorded wrapped to (-pi, pi], as recorders store it."""
    t = np.round(np.arange(0.0, 3.0 + 1e-9, 0.01), 10)
    theta = 3.0 * t
    wrapped = np.angle(np.exp(1j * theta))
    assert np.abs(np.diff(wrapped)).max() > 6  # the record really wraps
    x = np.sin(theta) / 3.0
    model = _equations(
        "DE",
        ["x"],
        ["x"],
        [("theta", "boundary")],
        "def f(x, theta, p):\n    return p[0] * cos(theta)\n",
        [1.0],
    )
    ds = Dataset.create(
        t,
        {"x": x, "theta": wrapped},
        {"x": "state", "theta": "boundary"},
        units={"x": "pu", "theta": "rad"},
        derivatives={"x": np.cos(theta)},
    )
    res = rollout(model, ds, mode="de")
    # linear play-in of the unwrapped angle: only the interpolation error of cos remains
    np.testing.assert_allclose(res["x"], x, atol=2e-5)


def test_knots_are_right_continuous_with_both_limits() -> None:
    t = np.arange(0.0, 0.06, 0.01)
    u = np.where(t < 0.03, t, 5.0 + t)  # sample at the event (0.03) is post-event
    T, Y = play_in_knots(t, u, events=(0.03,))
    assert list(T).count(0.03) == 2
    assert float(interpolate(T, Y, 0.03)[0]) == pytest.approx(5.03)
    assert float(interpolate(T, Y, 0.03 - 1e-12)[0]) == pytest.approx(0.03, abs=1e-9)
    assert float(interpolate(T, Y, 0.025)[0]) == pytest.approx(0.025)


# ---------------------------------------------------------------------------- toy generator


def _toy_generator(V_fault: float = 0.3, t_end: float = 3.0) -> Dataset:
    """A 2-state machine on a bus with voltage V(t) (dips during the fault) and angle theta(t)."""
    t = np.round(np.arange(0.0, t_end + 1e-9, 0.01), 10)

    def V(s):
        return V_fault if EVENTS[0] <= s < EVENTS[1] else 1.0 + 0.02 * math.sin(s)

    def theta(s):
        return 0.05 * s

    P_m = 1.0
    delta0 = math.asin(P_m / PMAX)

    def rhs(s, x):
        P_e = PMAX * V(s) * math.sin(x[0] - theta(s))
        return [OMEGA_B * (x[1] - 1.0), (P_m - P_e - D * (x[1] - 1.0)) / M]

    xs, x0 = [], [delta0, 1.0]
    cuts = [0.0, *EVENTS, t_end]
    for a, b in itertools.pairwise(cuts):
        sel = (t >= a) & ((t < b) if b < t_end else (t <= b))
        sol = solve_ivp(rhs, (a, b), x0, t_eval=t[sel], rtol=1e-12, atol=1e-12, method="DOP853")
        xs.append(sol.y.T)
        x0 = solve_ivp(rhs, (a, b), x0, rtol=1e-12, atol=1e-12, method="DOP853").y[:, -1]
    x = np.concatenate(xs)
    Vs = np.array([V(s) for s in t])
    th = theta(t)
    P_e = PMAX * Vs * np.sin(x[:, 0] - th)
    dx = np.array([rhs(s, xi) for s, xi in zip(t, x, strict=True)])
    return Dataset.create(
        t,
        {
            "delta": x[:, 0],
            "omega": x[:, 1],
            "P_e": P_e,
            "P_m": np.full_like(t, P_m),
            "V": Vs,
            "theta": th,
        },
        {
            "delta": "state",
            "omega": "state",
            "P_e": "algebraic",
            "P_m": "input",
            "V": "boundary",
            "theta": "boundary",
        },
        derivatives={"delta": dx[:, 0], "omega": dx[:, 1]},
        events=EVENTS,
    )


DE_SRC = (
    "def equation(delta, omega, P_m, P_e, p):\n"
    "    d_delta = p[0] * (omega - 1)\n"
    "    d_omega = (P_m - P_e - p[1] * (omega - 1)) / p[2]\n"
    "    return d_delta, d_omega\n"
)
AE_SRC = (
    "def equation(delta, V, theta, p):\n    P_e_ = p[0] * V * sin(delta - theta)\n    return P_e_\n"
)
LIB = [("P_m", "input"), ("P_e", "algebraic")]


def _models(pmax: float = PMAX, damping: float = D):
    de = _equations(
        "DE", ["delta", "omega"], ["delta", "omega"], LIB, DE_SRC, [OMEGA_B, damping, M]
    )
    ae = _equations(
        "AE", ["P_e"], ["delta"], [("V", "boundary"), ("theta", "boundary")], AE_SRC, [pmax]
    )
    return de, ae


@pytest.fixture(scope="module")
def toy() -> Dataset:
    return _toy_generator()


@pytest.mark.parametrize("mode", ["dae", "de"])
def test_true_model_reproduces_the_data(toy: Dataset, mode: str) -> None:
    de, ae = _models()
    res = rollout(de, toy, ae=ae if mode == "dae" else None, mode=mode)
    assert res.status == "ok"
    m = metrics(res, toy)
    assert m["mean"]["r2"] > 0.9999
    # "de" plays the oscillating P_e in by linear interpolation of 0.01 s samples: its O(h^2)
    # error is the floor there; "dae" computes P_e from the simulated state instead.
    assert m["mean"]["mape"] < (1e-3 if mode == "dae" else 0.1)  # percent
    assert m["mean"]["nrmse"] < (1e-5 if mode == "dae" else 1e-3)
    if mode == "dae":
        assert set(res.played_in) == {"P_m", "V", "theta"}
        np.testing.assert_allclose(res["P_e"], toy["P_e"], atol=1e-6)
    else:
        assert "P_e" in res.played_in


def test_a_model_is_put_at_equilibrium_where_the_recording_starts(toy: Dataset) -> None:
    """A model whose P_max is 5 % off the data's is not at rest at the recorded first state:
    solved for the rotor angle (and with the mechanical power free, the power held at its
    recorded value) it is."""
    de, ae = _models(pmax=1.05 * PMAX)
    start, report = at_equilibrium(de, toy, ("delta",), ae=ae)
    assert report["residual"]["after"] < 1e-9 < report["residual"]["before"]
    assert report["solved"]["delta"] == pytest.approx(math.asin(1.0 / (1.05 * PMAX)), rel=1e-9)
    assert float(start["delta"][0]) == report["solved"]["delta"]
    np.testing.assert_array_equal(start["delta"][1:], toy["delta"][1:])

    start, report = at_equilibrium(de, toy, ("delta", "P_m"), hold=("P_e",), ae=ae)
    assert report["solved"]["P_m"] == pytest.approx(float(toy["P_e"][0]), rel=1e-9)
    assert np.ptp(start["P_m"]) == 0.0
    with pytest.raises(ValueError, match="neither states"):
        at_equilibrium(de, toy, ("Q_m",), ae=ae)
    with pytest.raises(ValueError, match="algebraic variables"):
        at_equilibrium(de, toy, ("delta",), hold=("omega",), ae=ae)


def test_the_modes_at_the_recorded_operating_point_are_the_linearised_models(toy: Dataset) -> None:
    """The classical machine linearised at the recording's first sample: M s^2 + D s +
    Omega_b K = 0 with K = P_max V cos(delta - theta) (the algebraic P_e closed); with P_e
    played in and held ("de") the angle has no restoring force. A negative damping is
    unstable, and a model whose P_max is 5 % off does not rest at the recorded steady state."""
    from jaxdmd.rollout import modes

    de, ae = _models()
    k = PMAX * float(toy["V"][0]) * math.cos(float(toy["delta"][0] - toy["theta"][0]))
    roots = np.roots([M, D, OMEGA_B * k])
    m = modes(de, toy, ae=ae)
    got = np.array([complex(re, im) for re, im in m["eigenvalues"]])
    np.testing.assert_allclose(np.sort_complex(got), np.sort_complex(roots), rtol=1e-9)
    (osc,) = m["oscillatory"]
    assert osc["frequency_hz"] == pytest.approx(abs(roots[0].imag) / (2 * math.pi), rel=1e-9)
    assert osc["damping_ratio"] == pytest.approx(D / (2 * math.sqrt(M * OMEGA_B * k)), rel=1e-9)
    assert m["max_real"] == pytest.approx(-D / (2 * M), rel=1e-9) and m["max_real"] < 0
    assert max(abs(r) for r in m["rates"].values()) < 1e-6  # at rest where the recording is
    played = modes(de, toy, mode="de")
    np.testing.assert_allclose(sorted(e[0] for e in played["eigenvalues"]), [-D / M, 0.0],
                               atol=1e-12)  # fmt: skip
    assert modes(_models(damping=-D)[0], toy, ae=ae)["max_real"] == pytest.approx(D / (2 * M))
    off = modes(*_models(pmax=1.05 * PMAX)[:1], toy, ae=_models(pmax=1.05 * PMAX)[1])
    assert abs(off["rates"]["omega"]) > 1.0


def test_wrong_model_scores_worse(toy: Dataset) -> None:
    good = score(rollout(*_models()[:1], toy, ae=_models()[1]), toy)
    de, ae = _models(pmax=1.6 * PMAX)
    bad = score(rollout(de, toy, ae=ae), toy)
    assert bad["full"]["mean"]["r2"] < good["full"]["mean"]["r2"] - 0.05
    assert bad["fault"]["mean"]["nrmse"] > 100 * good["fault"]["mean"]["nrmse"]
    assert bad["full"]["mean"]["mape"] > good["full"]["mean"]["mape"]


def test_dae_without_algebraic_equations_is_a_setup_error(toy: Dataset) -> None:
    de, _ = _models()
    with pytest.raises(ValueError, match="P_e"):
        rollout(de, toy, mode="dae")


def test_divergence_is_flagged_not_raised() -> None:
    ds = _ramp_data(1.0)
    ds = Dataset.create(
        ds.t,
        {"x": np.ones_like(ds.t), "u": ds["u"]},
        {"x": "state", "u": "input"},
        derivatives={"x": ds["u"]},
        events=ds.events,
    )
    blow = _equations(
        "DE", ["x"], ["x"], [("u", "input")], "def f(x, u, p):\n    return p[0] * x * x\n", [1.0]
    )
    res = rollout(blow, ds, mode="de")  # x = 1 / (1 - t) blows up at t = 1
    assert res.diverged and 0.9 < res.diverged_at <= 1.01
    assert np.all(np.isnan(res["x"][ds.t > res.diverged_at]))
    s = score(res, ds)
    assert s["diverged"] and s["full"]["mean"]["r2"] == -np.inf
    nan = _equations(
        "DE", ["x"], ["x"], [("u", "input")], "def f(x, u, p):\n    return log(u - p[0])\n", [0.5]
    )
    res = rollout(nan, ds, mode="de")  # log of a negative number before t = 0.5
    assert res.diverged and res.diverged_at is not None


def test_block_model_and_compile_cache(toy: Dataset) -> None:
    """A user-given Block works; a refitted (new params) model reuses the compiled solve."""
    from jaxdmd.rollout import _compiled

    def fn(delta, omega, P_m, V, theta, p):
        P_e = (
            p[3] * V * np.sin(delta - theta)
            if False
            else p[3] * V * __import__("jax").numpy.sin(delta - theta)
        )
        return p[0] * (omega - 1), (P_m - P_e - p[1] * (omega - 1)) / p[2]

    block = Block(
        ("delta", "omega"),
        ("delta", "omega", "P_m", "V", "theta"),
        fn,
        np.array([OMEGA_B, D, M, PMAX]),
        key="toy",
    )
    res = rollout(block, toy, mode="dae")
    assert metrics(res, toy)["mean"]["r2"] > 0.9999
    before = _compiled.cache_info().misses
    block2 = Block(
        block.targets, block.arguments, fn, np.array([OMEGA_B, D, M, 1.1 * PMAX]), key="toy"
    )
    res2 = rollout(block2, toy, mode="dae")
    assert _compiled.cache_info().misses == before
    assert metrics(res2, toy)["mean"]["r2"] < metrics(res, toy)["mean"]["r2"]


# ---------------------------------------------------------------------------- metrics


def _known() -> tuple[Dataset, dict[str, np.ndarray]]:
    t = np.arange(5.0)
    a = np.array([1.0, 2.0, 3.0, 4.0, 5.0])  # bounded away from zero? min 1 >= 0.1 * 5: yes
    b = np.array([0.0, 1.0, 0.0, -1.0, 0.0])  # passes through zero
    ds = Dataset.create(
        t,
        {"a": a, "b": b},
        {"a": "state", "b": "state"},
        derivatives={"a": a, "b": b},
        events=(1.0, 2.0),
    )
    sim = {"a": a + np.array([0.0, 0.0, 0.3, 0.0, -0.4]), "b": b + 0.2}
    return ds, sim


def test_metrics_on_known_values() -> None:
    ds, sim = _known()
    m = metrics(sim, ds)
    pa, pb = m["per_state"]["a"], m["per_state"]["b"]
    # a: range 4; |x| >= 4 only at x = 4? max(|x|, 4) = [4, 4, 4, 4, 5]
    assert pa["mape"] == pytest.approx(100 * (0.3 / 4 + 0.4 / 5) / 5)
    assert pa["mape_plain"] == pytest.approx(100 * (0.3 / 3 + 0.4 / 5) / 5)
    assert pa["r2"] == pytest.approx(1 - (0.09 + 0.16) / 10.0)
    assert pa["nrmse"] == pytest.approx(math.sqrt(0.25 / 5) / 4)
    assert pa["nmae"] == pytest.approx(0.7 / 5 / 4)
    # b: range 2, floor 2 everywhere; plain MAPE undefined (passes through 0)
    assert pb["mape"] == pytest.approx(100 * 0.2 / 2)
    assert math.isnan(pb["mape_plain"])
    assert pb["r2"] == pytest.approx(1 - 5 * 0.04 / 2.0)
    assert m["mean"]["mape_plain"] == pytest.approx(pa["mape_plain"])  # NaN left out
    assert m["mean"]["r2"] == pytest.approx((pa["r2"] + pb["r2"]) / 2)
    # the fault window: events (1, 2) + 1 s -> samples t = 1, 2, 3; scale from the whole record
    assert fault_window(ds) == (1.0, 3.0)
    w = metrics(sim, ds, ["a"], window="fault")
    assert w["n_samples"] == 3
    assert w["per_state"]["a"]["nmae"] == pytest.approx(0.3 / 3 / 4)
    assert w["per_state"]["a"]["r2"] == pytest.approx(1 - 0.09 / 2.0)
