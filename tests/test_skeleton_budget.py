"""Size budgets: compiling and lowering a skeleton cost at most a constant times its source.

A checked skeleton is small (``MAX_SOURCE_CHARS``, ``MAX_NODES``, ``MAX_DEPTH``), but a
transformation that copies subtrees can still blow it up: comparison chains nested in comparison
chains used to double the rewritten tree at every level (k = 20 levels took gigabytes). These
tests bound the sizes after every transformation with node and instruction counts (not timings),
on the nested chains and on random whitelisted skeletons near the size limits.
"""

from __future__ import annotations

import time
import tracemalloc

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import jaxdmd  # noqa: F401  (enables float64)
from jaxdmd import interp
from jaxdmd.skeleton import (
    MAX_COMPILED_NODES,
    MAX_NODES,
    Skeleton,
    SkeletonError,
    compile_skeleton,
    sizes,
    try_compile,
)

VARIABLES = ("x", "y", "z")
# measured worst cases (below) are 2.6 rewritten nodes and 1.0 instructions per checked node
COMPILED_PER_NODE = 4
INSTRUCTIONS_PER_NODE = 2


def nested_chain(k: int, middle: str = "x") -> str:
    e = middle
    for _ in range(k):
        e = f"(y < {e} < y)"
    return f"def f(x, y, p):\n    return {e}\n"


@pytest.mark.parametrize("k", [10, 20, 40])
def test_nested_comparison_chains_compile_linearly(k):
    source = nested_chain(k)
    tracemalloc.start()
    start = time.perf_counter()
    try:
        result = try_compile(source, variables=["x", "y"], n_outputs=1)
        elapsed = time.perf_counter() - start
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert isinstance(result, Skeleton), result
    size = sizes(source, variables=["x", "y"])
    assert size["compiled"] <= COMPILED_PER_NODE * size["nodes"]
    assert size["instructions"] <= INSTRUCTIONS_PER_NODE * size["nodes"]
    assert peak < 20e6  # bytes of Python allocations (the old rewrite needed gigabytes at 20)
    assert elapsed < 10.0  # about 0.02 s alone, seconds on a loaded machine; a blow-up, minutes
    # and it computes what Python's chains compute
    x = np.array([-1.0, 0.0, 0.5, 2.0])
    y = np.array([0.0, 0.0, 1.0, 1.0])
    expected = x.copy()
    for _ in range(k):
        expected = ((y < expected) & (expected < y)).astype(float)
    np.testing.assert_array_equal(np.asarray(result({"x": x, "y": y}, np.zeros(0)))[0], expected)


def test_nested_chains_with_compound_middles_evaluate_each_operand_once():
    e = "x"
    for i in range(12):
        e = f"(y * {i + 2} < {e} + p[0] <= y + 1 > -y)"
    source = f"def f(x, y, p):\n    return {e}\n"
    sk = compile_skeleton(source, variables=["x", "y"], n_outputs=1)
    size = sizes(source, variables=["x", "y"])
    assert size["compiled"] <= COMPILED_PER_NODE * size["nodes"]
    x = np.linspace(-2, 2, 9)
    y = np.linspace(1, -1, 9)
    p = np.array([0.3])

    def naive(x, y, p):  # the same expression, evaluated by Python element by element
        return eval(e, {"p": p}, {"x": x, "y": y})  # our own text

    expected = [float(naive(a, b, p)) for a, b in zip(x, y, strict=True)]
    np.testing.assert_array_equal(np.asarray(sk({"x": x, "y": y}, p))[0], expected)
    program = interp.program_of(sk)
    assert program is not None
    np.testing.assert_array_equal(program.values([x, y], p[None])[0, 0], expected)


def test_budgets_reject_oversized_rewrites(monkeypatch):
    from jaxdmd.skeleton import compiling

    source = nested_chain(5)
    monkeypatch.setattr(compiling, "MAX_COMPILED_NODES", 20)
    error = try_compile(source, variables=["x", "y"], n_outputs=1)
    assert isinstance(error, SkeletonError)
    assert "too large" in error.reason and "rewritten" in error.reason
    monkeypatch.undo()
    monkeypatch.setattr(interp, "MAX_SSA", 4)
    interp._lower_cached.cache_clear()
    try:
        error = try_compile(source, variables=["x", "y"], n_outputs=1)
        assert isinstance(error, SkeletonError)
        assert "too large once lowered" in error.reason
    finally:
        interp._lower_cached.cache_clear()


# -- random whitelisted skeletons near the size limits -------------------------------------------

LEAVES = st.sampled_from(["x", "y", "z", "p[0]", "p[1]", "p[7]", "2.5", "1", "pi", "jnp.pi"])
FUNCTIONS_1 = ["jnp.sin", "cos", "np.exp", "math.log", "sqrt", "tanh", "abs", "jnp.square"]
FUNCTIONS_2 = ["jnp.maximum", "minimum", "arctan2"]
COMPARISONS = ["<", "<=", ">", ">=", "==", "!="]


def _compound(children: st.SearchStrategy[str]) -> st.SearchStrategy[str]:
    binop = st.tuples(children, st.sampled_from(["+", "-", "*", "/"]), children).map(
        lambda t: f"({t[0]} {t[1]} {t[2]})"
    )
    power = st.tuples(
        children, st.sampled_from(["2", "3", "7", "8", "-7", "(1 / 3)", "p[2]", "-p[3]"])
    ).map(lambda t: f"({t[0]} ** {t[1]})")
    chain = st.lists(st.tuples(st.sampled_from(COMPARISONS), children), min_size=1, max_size=4)
    compare = st.tuples(children, chain).map(
        lambda t: "(" + t[0] + "".join(f" {op} {b}" for op, b in t[1]) + ")"
    )
    ifexp = st.tuples(children, children, children).map(lambda t: f"({t[0]} if {t[1]} else {t[2]})")
    call1 = st.tuples(st.sampled_from(FUNCTIONS_1), children).map(lambda t: f"{t[0]}({t[1]})")
    call2 = st.tuples(st.sampled_from(FUNCTIONS_2), children, children).map(
        lambda t: f"{t[0]}({t[1]}, {t[2]})"
    )
    clip = st.tuples(children, children, children).map(
        lambda t: f"jnp.clip({t[0]}, {t[1]}, {t[2]})"
    )
    neg = children.map(lambda c: f"(-{c})")
    return st.one_of(compare, compare, binop, power, ifexp, call1, call2, clip, neg)


EXPRESSIONS = st.recursive(LEAVES, _compound, max_leaves=120)
# long chains of leaves: the rewrite's worst case (each operand is copied once)
LEAF_CHAINS = st.tuples(
    LEAVES, st.lists(st.tuples(st.sampled_from(COMPARISONS), LEAVES), min_size=1, max_size=30)
).map(lambda t: "(" + t[0] + "".join(f" {op} {b}" for op, b in t[1]) + ")")


@st.composite
def skeletons(draw: st.DrawFn) -> str:
    """A whitelisted skeleton of up to 30 assignments (locals feed later lines) and a return:
    up to several times the node limit, so that many lie near it."""
    lines = []
    for i in range(draw(st.integers(0, 30))):
        expression = draw(st.one_of(EXPRESSIONS, LEAF_CHAINS))
        if i and draw(st.booleans()):
            expression = f"({expression} < a{i - 1} < a{i - 1} * a0)"
        lines.append(f"    a{i} = {expression}")
    locals_ = [f"a{i}" for i in range(len(lines))]
    outputs = draw(st.lists(EXPRESSIONS, min_size=1, max_size=2))
    if locals_:
        outputs = [f"{o} + {locals_[-1]}" for o in outputs]
    body = "\n".join([*lines, f"    return {', '.join(outputs)}"])
    return f"def f(x, y, z, p):\n{body}\n"


@settings(
    max_examples=150,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
@given(skeletons())
def test_random_skeletons_stay_linear_after_every_transformation(source):
    try:
        size = sizes(source, variables=VARIABLES)
    except SkeletonError as error:  # only the whitelist's size limits reject these
        assert any(w in error.reason for w in ("too long", "too deeply", "characters long")), error
        return
    assert size["nodes"] <= MAX_NODES
    assert size["compiled"] <= COMPILED_PER_NODE * size["nodes"] <= MAX_COMPILED_NODES
    assert 0 < size["instructions"] <= INSTRUCTIONS_PER_NODE * size["nodes"]
    assert size["instructions"] <= interp.MAX_INSTRUCTIONS


def test_a_round_of_bombs_is_dropped_within_its_budget():
    """A proposer that answers only with the largest nested chains the whitelist lets through
    cannot stall a round: every answer is compiled within the size budgets (or rejected) and
    the round goes on."""
    import jax
    import jax.numpy as jnp

    from jaxdmd import search
    from jaxdmd.prompts import Contract, Variable
    from jaxdmd.proposers import Sample

    rng = np.random.default_rng(0)
    x, y = rng.normal(size=(2, 200))
    problem = search.Problem(
        variables={"x": jnp.asarray(x), "y": jnp.asarray(y)},
        targets=jnp.asarray(0.5 * x)[None],
        target_names=("x",),
        catalog=(Variable("y", "input"),),
    )
    contract = Contract(
        loop="DE", targets=("x",), states=(Variable("x", "state"),),
        library=(Variable("y", "input"),),
    )  # fmt: skip
    config = search.SearchConfig(n_islands=2, prompts_per_round=1, samples_per_prompt=8)
    state = search.init(problem, contract, jax.random.key(0), config)
    state, _ = search.prompts(state)
    bombs = [
        Sample(nested_chain(k).replace("def f(x, y, p)", "def equation(x, y, p)"), 0)
        for k in (20, 30, 40, 45, 47, 48, 49, 60)
    ]
    start = time.perf_counter()
    state, report = search.step(state, bombs)
    assert time.perf_counter() - start < 60  # was unbounded: k = 20 alone took gigabytes
    assert report.n_samples == len(bombs)
