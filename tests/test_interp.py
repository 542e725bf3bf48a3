"""Tests of jaxdmd.interp: lowered programs give the compiled skeleton's values and derivatives."""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

import jaxdmd  # noqa: F401  (float64)
from jaxdmd import interp
from jaxdmd.fit import FitConfig, Operator, fit_batch
from jaxdmd.skeleton import compile_skeleton

VARIABLES = ("x", "y", "u")
N = 64

CORPUS = [
    "def f(x, p):\n    return p[0] * x",
    "def f(x, y, p):\n    return p[0] * np.sin(x - p[1]) + p[2], p[3] * y ** 2 - x ** -2",
    "def f(x, y, p):\n    a = x * y\n    a += p[0]\n    b, c = a * p[1], np.exp(-p[2] * x)\n"
    "    return b + c, (b - c) / (1 + p[3] ** 2)",
    "def f(x, u, p):\n    return jnp.where(x > p[0], p[1] * u, p[2] * u), np.clip(x, p[3], p[4])",
    "def f(x, y, p):\n    return (p[0] * x if x < y else p[1] * y), np.maximum(p[2] * x, y)",
    "def f(x, y, p):\n    return np.minimum(x, p[0]) * np.arctan2(p[1] * y, x + 3), 0 < x < p[2]",
    "def f(x, u, p):\n    return np.abs(x) ** p[0] + np.sqrt(u) * p[1], np.tanh(p[2] * x) + np.pi",
    "def f(x, y, u, p):\n    return (np.cos(p[0] * x) * np.sinh(y) + np.cosh(p[1]) * np.arctan(u),"
    " np.log(u) * p[2] + np.sign(x) * np.square(p[3]) + np.e * np.tan(0.1 * p[4]))",
    "def f(x, y, p):\n    return np.arcsin(0.5 * np.tanh(p[0] * x))"
    " + np.arccos(0.3 * np.sin(y + p[1])),"
    " (x >= y) * p[2] + (x == x) * p[3] - (x != y) + (x <= 1) * (y > 0)",
    "def f(x, p):\n    return 3.5, p[0] * x ** (1 / 3) - x ** 0.5 + p[1] ** 3",
    "def f(x, y, p):\n    return x * y, x + p[0] - x",
    "def f(x, p):\n    return np.sqrt(x - x) + p[0] * x, p[1] * x ** 0",
    "def f(x, p):\n    t = p[0]\n    return t + p[0]",
]


def _data(seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {
        "x": rng.uniform(0.2, 2.0, N),
        "y": rng.uniform(-1.5, 1.5, N),
        "u": rng.uniform(0.5, 3.0, N),
    }


ROWS, REGS, PARAMS = 16, 16, 8  # padded shapes: one compile of the interpreter for every test


@functools.partial(jax.jit, static_argnums=3)
def _run(code, rows, p, n_regs):
    return interp.run(code, rows, p, n_regs)


def _interpret(program: interp.Program, rows: np.ndarray, p: np.ndarray):
    """Values [K, N] and Jacobian [K, P, N] (first len(p) columns) from the JAX interpreter."""
    assert program.n_regs <= REGS and len(rows) <= ROWS and len(p) <= PARAMS
    code = {k: jnp.asarray(v[0]) for k, v in interp.pack([program], [0], 256, 1).items()}
    x = np.zeros((ROWS, N))
    x[: len(rows)] = rows
    q = np.zeros(PARAMS)
    q[: len(p)] = p
    val, jac = _run(code, jnp.asarray(x), jnp.asarray(q), REGS)
    return np.asarray(val), np.asarray(jac)[:, : len(p)]


def _compare(sk, data, p: np.ndarray) -> None:
    program = interp.program_of(sk)
    assert program is not None
    args = [data[a] for a in program.arguments]
    ref = np.asarray(sk(data, jnp.asarray(p)))
    # host (NumPy) evaluation
    host = program.values(args, p[None])[0]
    np.testing.assert_allclose(host, ref, rtol=1e-12, atol=1e-12, equal_nan=True)
    # the JAX interpreter: whole program, then every per-output program
    rows = program.feature_values(args)
    val, jac = _interpret(program, rows, p)
    np.testing.assert_allclose(val, ref, rtol=1e-12, atol=1e-12, equal_nan=True)
    ref_jac = np.moveaxis(np.asarray(jax.jacfwd(lambda q: sk(data, q))(jnp.asarray(p))), -1, 1)
    ok = np.isfinite(ref_jac)
    scale = np.max(np.abs(ref_jac[ok]), initial=1.0)
    np.testing.assert_allclose(jac[ok], ref_jac[ok], rtol=1e-9, atol=1e-12 * scale)
    for k, part in enumerate(program.parts):
        v, j = _interpret(part, rows, p[part.params])
        np.testing.assert_allclose(v[0], ref[k], rtol=1e-12, atol=1e-12, equal_nan=True)
        jk = ref_jac[k][part.params]
        okk = np.isfinite(jk)
        np.testing.assert_allclose(j[0][okk], jk[okk], rtol=1e-9, atol=1e-12 * scale)
        # the host twin, for two restarts at once: the same values and derivatives as the JAX
        # interpreter; without care only where its tangent is finite (then it equals careful)
        q = np.stack([p[part.params], p[part.params]])
        for careful in (True, False):
            with np.errstate(all="ignore"):
                (hv,), (ht,) = interp.run_numpy(part, rows, q, careful=careful)
            hv = np.broadcast_to(hv, (2, N))
            ht = np.zeros((2, len(part.params), N)) if ht is None else ht
            ht = np.broadcast_to(ht, (2, len(part.params), N))
            np.testing.assert_allclose(hv[1], v[0], rtol=1e-12, atol=1e-12, equal_nan=True)
            fin = np.isfinite(ht[1]) if not careful else np.ones(ht[1].shape, bool)
            np.testing.assert_allclose(ht[1][fin], j[0][fin], rtol=1e-12, equal_nan=True)
        # a parameter the output does not use has a zero column
        unused = np.setdiff1d(np.arange(len(p)), part.params)
        assert np.all(ref_jac[k][unused][np.isfinite(ref_jac[k][unused])] == 0)


@pytest.mark.parametrize("source", CORPUS)
def test_corpus_values_and_derivatives(source: str) -> None:
    sk = compile_skeleton(source, variables=VARIABLES, n_outputs=None)  # type: ignore[arg-type]
    rng = np.random.default_rng(len(source))
    data = _data(1)
    for _ in range(3):
        p = rng.uniform(0.3, 1.5, max(1, sk.n_params)) * rng.choice(
            [-1.0, 1.0], max(1, sk.n_params)
        )
        p = np.abs(p) if "** p[0]" in source else p
        _compare(sk, data, p)


@pytest.mark.parametrize("source", CORPUS)
def test_host_values_are_the_host_twins_values_to_the_bit(source: str) -> None:
    """``evaluate_numpy`` (the values alone, what a host rollout calls at every step) computes
    exactly what ``run_numpy`` does, for several parameter rows at once."""
    sk = compile_skeleton(source, variables=VARIABLES, n_outputs=None)  # type: ignore[arg-type]
    program = interp.program_of(sk)
    assert program is not None
    data = _data(2)
    rows = program.feature_values([data[a] for a in program.arguments])
    q = np.random.default_rng(len(source)).uniform(0.3, 1.5, (3, max(1, sk.n_params)))
    got = interp.evaluate_numpy(program, list(rows), q, N)
    with np.errstate(all="ignore"):
        values, _ = interp.run_numpy(program, list(rows), q, tangents=False)
    want = np.stack([np.broadcast_to(v, (3, N)) for v in values], axis=1)
    assert got.shape == want.shape and got.dtype == np.float64
    assert np.array_equal(got.view(np.int64), want.view(np.int64))


@pytest.mark.parametrize("source", CORPUS)
def test_pointwise_values_are_the_diagonal_to_the_bit(source: str) -> None:
    """``pointwise_numpy`` (point b with parameter row b, what a batch of host rollouts calls)
    is the diagonal of ``Program.values`` bit for bit."""
    sk = compile_skeleton(source, variables=VARIABLES, n_outputs=None)  # type: ignore[arg-type]
    program = interp.program_of(sk)
    assert program is not None
    data = _data(2)
    args = [data[a] for a in program.arguments]
    q = np.random.default_rng(len(source)).uniform(0.3, 1.5, (N, max(1, sk.n_params)))
    got = interp.pointwise_numpy(program, args, q)
    full = program.values(args, q)  # [N, K, N]
    want = full[np.arange(N), :, np.arange(N)]
    assert got.shape == (N, program.n_outputs) and got.dtype == np.float64
    assert np.array_equal(got.view(np.int64), want.view(np.int64))


def _expressions() -> st.SearchStrategy[str]:
    leaves = st.one_of(
        st.sampled_from(["x", "y", "u", "p[0]", "p[1]", "p[2]", "np.pi"]),
        st.floats(-3, 3, allow_nan=False).map(lambda v: repr(round(v, 3))),
    )

    def extend(e: st.SearchStrategy[str]) -> st.SearchStrategy[str]:
        return st.one_of(
            st.tuples(e, st.sampled_from(["+", "-", "*", "/"]), e).map(
                lambda t: f"({t[0]} {t[1]} {t[2]})"
            ),
            e.map(lambda a: f"(-{a})"),
            st.tuples(st.sampled_from(["sin", "cos", "tanh", "abs", "arctan", "square"]), e).map(
                lambda t: f"np.{t[0]}({t[1]})"
            ),
            st.tuples(e, st.sampled_from(["2", "3", "-1", "0.5"])).map(
                lambda t: f"({t[0]}) ** {t[1]}"
            ),
            st.tuples(e, e).map(lambda t: f"np.maximum({t[0]}, {t[1]})"),
            st.tuples(e, e, e, e).map(lambda t: f"({t[0]} if {t[1]} < {t[2]} else {t[3]})"),
            st.tuples(e, e).map(lambda t: f"np.exp(-np.abs({t[0]})) * {t[1]}"),
        )

    return st.recursive(leaves, extend, max_leaves=12)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(_expressions(), min_size=1, max_size=3), st.integers(0, 2**31 - 1))
# NumPy's power takes a square root for a scalar 0.5, which differs from C's pow (and XLA's) at
# -inf and -0.0: a base of -inf (x / -0.0) and one of -0.0 (-(x * 0)) where x > 0
@example(["(x / -0.0) ** 0.5"], 0)
@example(["(-(x * 0.0)) ** 0.5"], 0)
# a parameter divided by the constant 0: the partial derivative is the number inf, and its
# product with the other parameters' zero tangents must be 0 on the host too, as in JAX
@example(["(p[1] / 0.0)"], 0)
def test_random_expressions(outputs: list[str], seed: int) -> None:
    source = (
        "def f(x, y, u, p):\n    t = "
        + outputs[0]
        + "\n    return "
        + ", ".join(["t + p[0]", *outputs[1:]])
    )
    sk = compile_skeleton(source, variables=VARIABLES, n_outputs=len(outputs))
    p = np.random.default_rng(seed).uniform(-2, 2, max(1, sk.n_params))
    _compare(sk, _data(seed % 7), p)


def test_replaced_function_has_no_program() -> None:
    sk = compile_skeleton(CORPUS[0], variables=VARIABLES, n_outputs=1)
    assert interp.program_of(sk) is not None
    assert interp.program_of(dataclasses.replace(sk, fn=lambda x, p: p[0] * x * 2)) is None
    assert interp.program_of(dataclasses.replace(sk, arguments=("y",))) is None


def test_hoisting_and_output_programs() -> None:
    src = "def f(x, y, u, p):\n    return p[0] * np.sin(x - y) * u, p[1] * np.exp(x * y) + p[2]"
    program = interp.program_of(compile_skeleton(src, variables=VARIABLES, n_outputs=2))
    assert program is not None
    # the parameter-free parts (sin(x - y), u and exp(x * y); the product is (p0 * sin) * u)
    # are three host-side feature rows
    assert program.feature_values([_data()[a] for a in ("x", "y", "u")]).shape == (3, N)
    assert [part.params.tolist() for part in program.parts] == [[0], [1, 2]]
    assert all(part.length <= 5 for part in program.parts)


NONLINEAR = """def equation(x, y, u, p):
    return p[0] * np.exp(-p[1] * x) + p[2] * y, p[3] * u / (1 + p[4] * u) + p[5] * np.sin(y)"""
TRUE = np.array([2.0, 1.3, -0.7, 3.0, 0.8, 0.25])


@pytest.fixture(scope="module")
def nonlinear_fit():
    rng = np.random.default_rng(11)
    n = 800
    data = {
        "x": rng.uniform(0, 3, n),
        "y": rng.uniform(-1, 1, n),
        "u": rng.uniform(0.1, 4, n),
    }
    sk = compile_skeleton(NONLINEAR, variables=VARIABLES, n_outputs=2)
    clean = np.asarray(sk(data, TRUE))
    sigma = 0.01 * np.std(clean, axis=1)
    targets = clean + sigma[:, None] * rng.standard_normal(clean.shape)
    return sk, data, targets, sigma


def test_fit_recovers_nonlinear_parameters(nonlinear_fit) -> None:
    sk, data, targets, sigma = nonlinear_fit
    (res,) = fit_batch([sk], data, targets, key=jax.random.key(3))
    assert res.error is None
    # standard errors from the Jacobian at the truth: the estimate is within a few of them
    jac = np.asarray(jax.jacfwd(lambda q: sk(data, q))(jnp.asarray(TRUE)))  # [K, N, P]
    cov = np.zeros((6, 6))
    for k in range(2):
        cov += jac[k].T @ jac[k] / sigma[k] ** 2
    se = np.sqrt(np.diag(np.linalg.inv(cov)))
    z = (res.params - TRUE) / se
    assert np.all(np.abs(z) < 5), z
    floor = sigma**2 / np.var(targets, axis=1)
    np.testing.assert_allclose(res.losses, floor, rtol=0.2)


def test_interpreter_matches_compiled_path(nonlinear_fit) -> None:
    sk, data, targets, _ = nonlinear_fit
    other = compile_skeleton(
        "def g(x, y, u, p):\n"
        "    return p[0] * np.tanh(p[1] * x), p[2] * u + p[3] / (u + p[4] ** 2)",
        variables=VARIABLES, n_outputs=2,
    )  # fmt: skip
    n = targets.shape[1]
    index = np.clip(np.arange(n)[:, None] + np.arange(5)[None, :] - 2, 0, n - 1)
    operator = Operator(index, np.full((n, 5), 0.2))
    for op in (None, operator):
        key = jax.random.key(5)
        host = fit_batch([sk, other], data, targets, key=key, operator=op)
        for config in (FitConfig(backend="xla"), FitConfig(interpreter=False)):
            slow = fit_batch([sk, other], data, targets, key=key, operator=op, config=config)
            for a, b in zip(host, slow, strict=True):
                assert a.error is None and b.error is None
                np.testing.assert_allclose(a.losses, b.losses, rtol=1e-6, atol=1e-12)
                np.testing.assert_allclose(a.restart_losses, b.restart_losses, rtol=1e-6)


def test_host_fit_where_a_zero_meets_an_infinite_derivative() -> None:
    # d sqrt(u)/du is infinite at u = p0 * 0 = 0, and du/dp0 is 0: the chain rule's product is
    # NaN unless a zero factor wins (as in JAX's symbolic zeros and the JAX interpreter)
    src = "def f(x, p):\n    return np.sqrt(p[0] * 0) + p[1] * np.exp(p[2] * x)"
    sk = compile_skeleton(src, variables=VARIABLES, n_outputs=1)
    program = interp.program_of(sk)
    assert program is not None
    (part,) = program.parts
    rows = program.feature_values([_data()["x"]])
    q = np.array([[1.0, 2.0, 0.5]])
    with np.errstate(all="ignore"):
        _, (careful,) = interp.run_numpy(part, rows, q, careful=True)
        _, (careless,) = interp.run_numpy(part, rows, q, careful=False)
    assert np.all(careful[:, 0] == 0) and np.all(np.isnan(careless[:, 0]))
    x = _data()["x"]
    (res,) = fit_batch([sk], {"x": x}, 2.0 * np.exp(0.5 * x), key=jax.random.key(0))
    assert res.error is None
    np.testing.assert_allclose(res.params[1:], [2.0, 0.5], rtol=1e-6)
