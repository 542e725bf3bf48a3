"""Tests of jaxdmd.fit: parameter recovery, NMSE, dropped candidates, determinism."""

from __future__ import annotations

import dataclasses

import jax
import numpy as np
import pytest

import jaxdmd  # noqa: F401  (float64)
from jaxdmd.fit import FitConfig, FitResult, fit_batch, nmse
from jaxdmd.skeleton import compile_skeleton

VARIABLES = ("delta", "omega", "x", "u")
N = 600
TRUE_LIN = np.array([377.0, 0.016, -0.03, 2.5])  # d0 = p0 (omega - 1); d1 = p1 u + p2 x + p3
TRUE_NL = np.array([1.8, 0.35, 0.2, -4.0])  # d0 = p0 sin(delta - p1) + p2; d1 = p3 x
SIGMA = (0.05, 0.002)

LINEAR = """def equation(delta, omega, x, u, p):
    return p[0] * (omega - 1), p[1] * u + p[2] * x + p[3]"""
NONLINEAR = """def equation(delta, x, p):
    return p[0] * np.sin(delta - p[1]) + p[2], p[3] * x"""
NAN = """def equation(x, p):
    return p[0] * np.sqrt(-1 - x ** 2), p[1] * x"""
UNKNOWN = """def equation(x, p):
    return p[0] * x, p[1] * x"""


def _data(seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 6, N)
    return {
        "delta": 0.9 + 0.6 * np.sin(1.3 * t) + 0.05 * rng.standard_normal(N),
        "omega": 1 + 2e-3 * np.sin(2.1 * t + 0.4),
        "x": np.cos(0.7 * t) + 0.3 * rng.standard_normal(N),
        "u": 6 + 0.5 * np.sin(0.4 * t),
    }


def _skeleton(text: str, name: str):
    sk = compile_skeleton(text, variables=VARIABLES, n_outputs=2)
    return dataclasses.replace(sk, name=name)


@pytest.fixture(scope="module")
def linear_problem():
    data = _data(1)
    rng = np.random.default_rng(2)
    clean = np.stack(
        [
            TRUE_LIN[0] * (data["omega"] - 1),
            TRUE_LIN[1] * data["u"] + TRUE_LIN[2] * data["x"] + TRUE_LIN[3],
        ]
    )
    targets = clean + np.array(SIGMA)[:, None] * rng.standard_normal(clean.shape)
    return data, targets


@pytest.fixture(scope="module")
def batch():
    """One mixed batch: linear, nonlinear, NaN, untraceable, unknown variable (one compile)."""
    data = _data(3)
    rng = np.random.default_rng(4)
    clean = np.stack(
        [TRUE_NL[0] * np.sin(data["delta"] - TRUE_NL[1]) + TRUE_NL[2], TRUE_NL[3] * data["x"]]
    )
    targets = clean + 0.01 * rng.standard_normal(clean.shape)
    lin = _skeleton(LINEAR, "linear")
    broken = dataclasses.replace(lin, name="broken", fn=_raises)
    unknown = dataclasses.replace(lin, name="unknown", arguments=("x", "nope"))
    cands = [_skeleton(NONLINEAR, "nonlinear"), _skeleton(NAN, "nan"), broken, unknown, lin]
    results = fit_batch(cands, data, targets, key=jax.random.key(0))
    return data, targets, cands, results


def _raises(*args):
    raise TypeError("this candidate cannot be traced")


def test_linear_matches_least_squares(linear_problem) -> None:
    data, targets = linear_problem
    (res,) = fit_batch([_skeleton(LINEAR, "lin")], data, targets, key=jax.random.key(1))
    assert res.error is None
    # exact least squares per equation, and its standard errors
    a0 = (data["omega"] - 1)[:, None]
    a1 = np.stack([data["u"], data["x"], np.ones(N)], axis=1)
    for cols, a, k in (([0], a0, 0), ([1, 2, 3], a1, 1)):
        coef = np.linalg.lstsq(a, targets[k], rcond=None)[0]
        np.testing.assert_allclose(res.params[cols], coef, rtol=1e-6, atol=1e-9)
        cov = SIGMA[k] ** 2 * np.linalg.inv(a.T @ a)
        z = (res.params[cols] - TRUE_LIN[cols]) / np.sqrt(np.diag(cov))
        assert np.all(np.abs(z) < 5), z
    # near the noise floor: NMSE = sigma^2 / var
    floor = np.array(SIGMA) ** 2 / np.var(targets, axis=1)
    np.testing.assert_allclose(res.losses, floor, rtol=0.25)
    assert res.score == pytest.approx(-np.mean(res.losses))


def test_nonlinear_recovered_with_restarts(batch) -> None:
    _, _, _, results = batch
    res = results[0]
    assert res.error is None
    angle = (res.params[1] - TRUE_NL[1] + np.pi) % (2 * np.pi) - np.pi
    if res.params[0] < 0:  # p0 sin(a - p1) = -p0 sin(a - p1 - pi)
        angle = (angle + 2 * np.pi) % (2 * np.pi) - np.pi
    assert abs(abs(res.params[0]) - TRUE_NL[0]) < 0.01
    assert abs(angle) < 0.01 or abs(abs(angle) - np.pi) < 0.01
    np.testing.assert_allclose(res.params[[2, 3]], TRUE_NL[[2, 3]], atol=0.01)
    assert res.restart_losses.shape == (FitConfig().restarts, 2)


def test_losses_are_per_output_nmse(batch) -> None:
    data, targets, cands, results = batch
    for sk, res in zip(cands, results, strict=True):
        if res.error is None:
            pred = np.asarray(sk(data, res.params))
            np.testing.assert_allclose(res.losses, nmse(pred, targets), rtol=1e-8)
            assert res.losses.shape == (2,)


def test_bad_candidates_dropped_batch_survives(batch) -> None:
    _, _, _, results = batch
    nonlinear, nan, broken, unknown, lin = results
    assert nan.score == -np.inf and "non-finite" in nan.error
    assert broken.score == -np.inf and "failed to trace" in broken.error
    assert "cannot be traced" in broken.error
    assert unknown.score == -np.inf and "nope" in unknown.error
    for good in (nonlinear, lin):
        assert good.error is None and np.isfinite(good.score)
        assert np.all(np.isfinite(good.params))
    assert all(isinstance(r, FitResult) for r in results)


def test_deterministic_given_key(batch) -> None:
    data, targets, cands, results = batch
    again = fit_batch(cands, data, targets, key=jax.random.key(0))
    for a, b in zip(results, again, strict=True):
        np.testing.assert_array_equal(a.params, b.params)
        np.testing.assert_array_equal(a.losses, b.losses)
        assert a.error == b.error


def test_weights_enter_the_nmse(linear_problem) -> None:
    data, targets = linear_problem
    w = np.ones(N)
    w[: N // 2] = 0.0
    (res,) = fit_batch(
        [_skeleton(LINEAR, "lin")], data, targets, key=jax.random.key(1), weights=w,
        config=FitConfig(restarts=2),
    )  # fmt: skip
    sk = _skeleton(LINEAR, "lin")
    pred = np.asarray(sk(data, res.params))
    np.testing.assert_allclose(res.losses, nmse(pred, targets, w), rtol=1e-8)
    a1 = np.stack([data["u"], data["x"], np.ones(N)], axis=1)[N // 2 :]
    coef = np.linalg.lstsq(a1, targets[1, N // 2 :], rcond=None)[0]
    np.testing.assert_allclose(res.params[1:], coef, rtol=1e-6)


def test_outputs_sharing_a_nonlinear_parameter_are_fitted_together() -> None:
    # p[1] enters both outputs, nonlinearly in the first: one least-squares problem of three
    # parameters, whichever backend runs it (host NumPy or the jitted interpreter)
    data = _data(5)
    rng = np.random.default_rng(6)
    true = np.array([1.5, 0.8, -2.0])
    clean = np.stack(
        [true[0] * np.exp(-true[1] * data["x"]), true[1] * data["u"] + true[2] * data["x"]]
    )
    targets = clean + 0.002 * rng.standard_normal(clean.shape)
    sk = _skeleton(
        "def equation(x, u, p):\n    return p[0] * np.exp(-p[1] * x), p[1] * u + p[2] * x",
        "coupled",
    )
    fits = [
        fit_batch([sk], data, targets, key=jax.random.key(2), config=FitConfig(backend=b))[0]
        for b in ("host", "xla")
    ]
    for res in fits:
        assert res.error is None
        np.testing.assert_allclose(res.params, true, rtol=5e-3)
    np.testing.assert_allclose(fits[0].losses, fits[1].losses, rtol=1e-8)
    with pytest.raises(ValueError, match="backend"):
        fit_batch([sk], data, targets, key=jax.random.key(2), config=FitConfig(backend="gpu"))


def test_bad_data_raises() -> None:
    data = _data()
    with pytest.raises(ValueError, match="non-finite"):
        fit_batch([], data, np.full((2, N), np.nan), key=jax.random.key(0))
    with pytest.raises(ValueError, match="shape"):
        fit_batch([], {"x": np.ones(3)}, np.ones((2, N)), key=jax.random.key(0))


def test_operator_matched_fit_removes_the_smoothing_bias():
    """Targets smoothed by an operator: fitting S f(x) recovers p, fitting f(x) does not."""
    from jaxdmd.fit import Operator

    n = 600
    t = np.linspace(0.0, 6.0, n)
    x = np.sin(7.0 * t) + 0.3 * np.cos(23.0 * t)
    width = 15  # a moving average: a strong smoothing, like a derivative estimator's
    index = np.clip(np.arange(n)[:, None] + np.arange(width)[None, :] - width // 2, 0, n - 1)
    weight = np.full((n, width), 1.0 / width)
    truth = 2.5 * x  # "derivative" of the toy system: f(x) = p x with p = 2.5
    smoothed = np.sum(truth[index] * weight, axis=1)
    sk = compile_skeleton("def f(x, p):\n    return p[0] * x\n", variables=["x"], n_outputs=1)
    key = jax.random.key(0)
    (plain,) = fit_batch([sk], {"x": x}, smoothed[None], key=key)
    (matched,) = fit_batch(
        [sk], {"x": x}, smoothed[None], key=key, operator=Operator(index, weight)
    )
    assert abs(matched.params[0] - 2.5) < 1e-9 and matched.losses[0] < 1e-20
    assert abs(plain.params[0] - 2.5) > 0.1  # the bias the operator removes


def test_chunked_evaluation_is_bit_identical(monkeypatch) -> None:
    """The host fit evaluates the linear shortcut's probes and the operator's product a few rows
    at a time (memory, issue #15): any chunk size gives the same numbers to the last bit."""
    from jaxdmd import fit, lm
    from jaxdmd.fit import Operator

    data = _data(3)
    rng = np.random.default_rng(4)
    width = 9
    index = np.clip(np.arange(N)[:, None] + np.arange(width)[None, :] - width // 2, 0, N - 1)
    weight = rng.normal(size=(N, width))
    targets = np.stack([rng.normal(size=N), 1 + 0.1 * rng.normal(size=N)])
    sources = [
        LINEAR,
        NONLINEAR,
        "def equation(delta, omega, x, u, p):\n"
        "    return p[0] * omega + p[1] * np.cos(delta), p[0] * x + p[2] * u + p[3]\n",
        "def equation(delta, omega, x, u, p):\n"
        "    return p[0] * omega + p[1] * np.tanh(p[2] * x), p[3] * u * x + p[4]\n",
    ]
    skeletons = [
        compile_skeleton(s, variables=VARIABLES, n_outputs=2) for s in sources
    ]  # fmt: skip
    w = rng.uniform(0.5, 2.0, size=N)

    def run() -> list:
        return fit_batch(
            skeletons, data, targets, key=jax.random.key(1), weights=w,
            operator=Operator(index, weight),
        )  # fmt: skip

    whole = run()
    for chunk in (1, 3 * N + 1):
        monkeypatch.setattr(lm, "BAND_CHUNK", chunk)
        monkeypatch.setattr(fit, "PROBE_CHUNK", chunk)
        for a, b in zip(whole, run(), strict=True):
            assert a.params.tobytes() == b.params.tobytes()
            assert a.losses.tobytes() == b.losses.tobytes()
            assert a.restart_losses.tobytes() == b.restart_losses.tobytes()
    big = rng.normal(size=(5, 2, N))
    monkeypatch.setattr(lm, "BAND_CHUNK", 1)
    band = lm.band_matrix(index, weight)
    one = np.ascontiguousarray((band @ big.reshape(-1, N).T).T).reshape(big.shape)
    assert lm.apply_band(band, big).tobytes() == one.tobytes()


def test_a_batch_holds_the_feature_rows_of_the_candidates_being_fitted_only() -> None:
    """At long recordings a batch's feature rows (each candidate's parameter-free terms) do not
    fit in memory together: a candidate's rows are dropped when it is fitted, so the memory of
    a batch does not grow with its candidates (the fits are the same)."""
    import tracemalloc

    rng = np.random.default_rng(0)
    n = 20000
    names = [f"x{i}" for i in range(8)]
    data = {v: rng.normal(size=n) for v in names}
    pairs = [(a, b) for a in names for b in names if a < b]
    sources = [
        f"def f({', '.join(names)}, p):\n"
        f"    return p[0] * {a} * {b} + p[1] * {a} * {a} * {b} + p[2] * {b} * {b}"
        f" + p[3] * {a} * {b} * {b}\n"
        for a, b in pairs
    ]
    skeletons = [compile_skeleton(s, variables=tuple(names), n_outputs=1) for s in sources]
    target = data["x0"] * data["x1"] + 0.1 * rng.normal(size=n)

    def peak(k: int) -> tuple[int, list[FitResult]]:
        tracemalloc.start()
        results = fit_batch(skeletons[:k], data, target, key=jax.random.key(0))
        _, top = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        return top, results

    few, first = peak(3)
    many, results = peak(len(skeletons))
    rows = len(skeletons) * 4 * n * 8  # bytes of all the candidates' feature rows
    assert many < 1.5 * few and many < rows / 2, (few, many, rows)
    assert [r.params.tolist() for r in results[:3]] == [r.params.tolist() for r in first]


def test_the_operator_shares_its_buffers_with_its_band_matrix() -> None:
    """At long recordings the matched operator is the largest array a fit holds besides the
    data: its indices are 32-bit, and the sparse matrix the host fit multiplies by is built
    once, on the operator's own buffers."""
    from jaxdmd.fit import Operator

    n, width = 1000, 7
    index = np.clip(np.arange(n)[:, None] + np.arange(width)[None, :] - width // 2, 0, n - 1)
    weight = np.random.default_rng(0).normal(size=(n, width))
    operator = Operator(index, weight)
    band = operator.band
    assert operator.band is band and operator.index.dtype == np.int32
    assert np.shares_memory(band.indices, np.asarray(operator.index))
    assert np.shares_memory(band.data, np.asarray(operator.weight))
    y = np.random.default_rng(1).normal(size=n)
    np.testing.assert_allclose(band @ y, np.asarray(operator(y)), rtol=1e-12, atol=1e-12)
    # sent to a worker, it travels without its band (a copy there), and builds it there
    import pickle

    payload = pickle.dumps(operator)
    assert len(payload) < 1.5 * (index.size * 4 + weight.nbytes)
    sent = pickle.loads(payload)
    assert np.shares_memory(sent.band.data, np.asarray(sent.weight))
    np.testing.assert_array_equal(sent.band @ y, band @ y)


def test_a_lowered_candidate_is_solved_one_group_of_outputs_at_a_time() -> None:
    """At long recordings the predictions of a candidate at its probes (``[P + 3, K, N]``) are
    the largest array of a fit: a lowered candidate is solved a group of outputs (linked by
    shared parameters) at a time, so only one group's predictions are held. The fit is the
    whole candidate's (through its traced function), including an output with no parameter."""
    import tracemalloc

    rng = np.random.default_rng(3)
    n = 20000
    names = ("x", "y", "z")
    data = {v: rng.normal(size=n) for v in names}
    x, y, z = (data[v] for v in names)
    targets = np.stack([
        1.5 * x - 0.5 * y * z + 0.2,
        -2.0 * y + 0.7 * x * x,
        3.0 * z - 2.0 * y + 0.1 * rng.normal(size=n),
        x * y + 0.3 * rng.normal(size=n),
        *(j * x - z for j in range(4)),
    ])  # fmt: skip
    more = "".join(f"            p[{9 + 2 * j}] * x + p[{10 + 2 * j}] * z,\n" for j in range(4))
    source = (
        "def f(x, y, z, p):\n"
        "    return (p[0] * x + p[1] * y * z + p[2] + p[3] * x * y * z,\n"
        "            p[4] * y + p[5] * x * x + p[6] * x * z,\n"
        "            p[7] * z + p[4] * y + p[8] * y * y,\n"
        "            x * y,\n" + more + "            )\n"
    )
    sk = compile_skeleton(source, variables=names, n_outputs=8)
    key = jax.random.key(0)
    tracemalloc.start()
    (grouped,) = fit_batch([sk], data, targets, key=key)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    (whole,) = fit_batch([sk], data, targets, key=key, config=FitConfig(interpreter=False))
    assert grouped.error is None and whole.error is None
    np.testing.assert_allclose(grouped.params, whole.params, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(grouped.losses, whole.losses, rtol=1e-9)
    np.testing.assert_allclose(grouped.params[[0, 1, 2, 4, 5, 7]], [1.5, -0.5, 0.2, -2, 0.7, 3],
                               atol=0.02)  # fmt: skip
    predictions = (sk.n_params + 3) * 8 * n * 8  # bytes of the candidate's [P + 3, K, N]
    assert peak < predictions / 2, (peak, predictions)
