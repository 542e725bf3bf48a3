"""Skeletons of the normal kind: extraction, checking, compilation and evaluation."""

import pickle
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxdmd  # noqa: F401  (enables float64)
from jaxdmd.skeleton import (
    MAX_PARAMS,
    Skeleton,
    SkeletonError,
    check,
    compile_skeleton,
    extract,
    probe,
    try_compile,
)

LIBRARY = ("delta", "omega", "e_qp", "P_m", "P_e", "i_d", "V_t")

SWING = """\
def equation(delta, omega, e_qp, P_m, P_e, i_d, p):
    d_delta = p[0] * (omega - 1.0)
    d_omega = p[1] * P_m + p[2] * P_e + p[3] * (omega - 1)
    d_eqp = p[4] * e_qp + p[5] * i_d + p[6]
    return d_delta, d_omega, d_eqp
"""


def swing_reference(v, p):
    return jnp.stack(
        [
            p[0] * (v["omega"] - 1.0),
            p[1] * v["P_m"] + p[2] * v["P_e"] + p[3] * (v["omega"] - 1),
            p[4] * v["e_qp"] + p[5] * v["i_d"] + p[6],
        ]
    )


@pytest.fixture
def data():
    rng = np.random.default_rng(0)
    return {name: jnp.asarray(rng.uniform(0.5, 1.5, 50)) for name in LIBRARY}


def test_swing_compiles_and_matches_hand_written(data):
    sk = compile_skeleton(SWING, variables=LIBRARY, n_outputs=3)
    assert isinstance(sk, Skeleton)
    assert sk.name == "equation"
    assert sk.arguments == ("delta", "omega", "e_qp", "P_m", "P_e", "i_d")
    assert (sk.n_params, sk.n_outputs, sk.n_constants) == (7, 3, 2)
    assert sk.requests == ()
    assert sk.length > 20
    p = jnp.linspace(-1.0, 2.0, 7)
    out = sk(data, p)
    assert out.shape == (3, 50) and out.dtype == jnp.float64
    np.testing.assert_allclose(out, swing_reference(data, p), rtol=1e-14)
    raw = sk.fn(*(data[a] for a in sk.arguments), p)
    assert isinstance(raw, tuple) and len(raw) == 3


def test_source_is_normalised_and_recompiles(data):
    sk = compile_skeleton(SWING, variables=LIBRARY, n_outputs=3)
    assert "return (d_delta, d_omega, d_eqp)" in sk.source
    again = compile_skeleton(sk.source, variables=LIBRARY, n_outputs=3)
    assert again == sk  # fn and requests are not compared
    p = jnp.ones(7)
    np.testing.assert_array_equal(again(data, p), sk(data, p))


def test_jit_vmap_grad(data):
    sk = compile_skeleton(SWING, variables=LIBRARY, n_outputs=3)
    p = jnp.linspace(-1.0, 2.0, 7)
    np.testing.assert_allclose(jax.jit(sk)(data, p), sk(data, p), rtol=1e-14)
    batch = jnp.stack([p, 2 * p, -p])
    outs = jax.vmap(sk, in_axes=(None, 0))(data, batch)
    assert outs.shape == (3, 3, 50)
    np.testing.assert_allclose(outs[1], sk(data, 2 * p), rtol=1e-14)

    def loss(p):
        return jnp.sum(sk(data, p) ** 2)

    g = jax.jit(jax.grad(loss))(p)
    g_ref = jax.grad(lambda p: jnp.sum(swing_reference(data, p) ** 2))(p)
    np.testing.assert_allclose(g, g_ref, rtol=1e-12)
    per_sample = jax.vmap(lambda v: sk(v, p), in_axes=({k: 0 for k in data},))(data)
    assert per_sample.shape == (50, 3)


def test_math_functions_namespaces_and_constants(data):
    text = """
    def f(delta, omega, V_t, p):
        a = jnp.sin(delta) + np.cos(delta) + math.tan(delta / 4) + jax.numpy.exp(-omega)
        b = sqrt(abs(V_t)) * tanh(omega) - arctan2(delta, omega) + math.atan(omega) + sinh(1.0)
        c = where(delta > omega, delta, omega) + clip(V_t, 0.8, 1.2) + maximum(delta, p[0])
        d = minimum(omega, 1) + sign(delta - 1) + square(V_t) + jnp.pi * pi + math.e + np.log(V_t)
        a += b
        return a + c + d
    """
    sk = compile_skeleton(text, variables=LIBRARY, n_outputs=1)
    assert sk.arguments == ("delta", "omega", "V_t") and sk.n_params == 1
    d, w, v = data["delta"], data["omega"], data["V_t"]
    p = jnp.array([0.9])
    ref = (
        jnp.sin(d) + jnp.cos(d) + jnp.tan(d / 4) + jnp.exp(-w)
        + jnp.sqrt(jnp.abs(v)) * jnp.tanh(w) - jnp.arctan2(d, w) + jnp.arctan(w) + jnp.sinh(1.0)
        + jnp.where(d > w, d, w) + jnp.clip(v, 0.8, 1.2) + jnp.maximum(d, 0.9)
        + jnp.minimum(w, 1) + jnp.sign(d - 1) + jnp.square(v) + jnp.pi**2 + np.e + jnp.log(v)
    )  # fmt: skip
    np.testing.assert_allclose(sk(data, p)[0], ref, rtol=1e-13)


def test_conditional_expressions_and_chained_comparisons_are_jit_safe(data):
    text = """
    def f(delta, omega, p):
        lim = p[0] if delta > 1.0 else p[1]
        inside = 0.8 < omega <= 1.2
        return lim * inside + (omega < delta)
    """
    sk = compile_skeleton(text, variables=LIBRARY, n_outputs=1)
    d, w = data["delta"], data["omega"]
    p = jnp.array([2.0, -3.0])
    ref = jnp.where(d > 1.0, 2.0, -3.0) * ((w > 0.8) & (w <= 1.2)) + (w < d)
    np.testing.assert_allclose(jax.jit(sk)(data, p)[0], ref)
    assert jax.grad(lambda p: sk(data, p).sum())(p).shape == (2,)


def test_powers(data):
    text = """
    def f(omega, V_t, p):
        a, b, c = omega ** 2, V_t ** -1.5, omega ** (1 / 3)
        return a, b, c, V_t ** p[0], omega ** -p[1], (omega ** 8) ** 8
    """
    sk = compile_skeleton(text, variables=LIBRARY, n_outputs=6)
    w, v = data["omega"], data["V_t"]
    p = jnp.array([0.7, 1.3])
    ref = jnp.stack([w**2, v**-1.5, w ** (1 / 3), v**0.7, w**-1.3, w**64])
    np.testing.assert_allclose(sk(data, p), ref, rtol=1e-12)


def test_constants_cannot_raise_python_errors(data):
    text = """
    def f(omega, p):
        return omega * (1.0 / (2 - 2)) + 0 ** -1, p[0] * ((1e6 * 1e6 * 1e6) ** 8) ** 8
    """
    sk = compile_skeleton(text, variables=LIBRARY, n_outputs=2)
    out = sk(data, jnp.ones(1))
    assert not jnp.isfinite(out).any()


def test_single_output_constant_output_and_broadcasting(data):
    sk = compile_skeleton("def g(p):\n    return p[0]\n", variables=LIBRARY, n_outputs=1)
    assert sk.arguments == () and sk.n_params == 1
    out = sk(data, jnp.array([3.0]))
    assert out.shape == (1, 50)
    np.testing.assert_array_equal(out, 3.0)
    sk2 = compile_skeleton(
        "def g(omega, p):\n    return 1.0, omega\n", variables=LIBRARY, n_outputs=2
    )
    assert sk2.n_params == 0 and sk2.n_constants == 1
    out2 = sk2(data, jnp.zeros(0))
    assert out2.shape == (2, 50)
    np.testing.assert_array_equal(out2[0], 1.0)


def test_argument_order_and_subset(data):
    sk = compile_skeleton(
        "def f(P_e, delta, p):\n    return P_e - p[0] * delta\n", variables=LIBRARY, n_outputs=1
    )
    assert sk.arguments == ("P_e", "delta")
    p = jnp.array([2.0])
    np.testing.assert_allclose(sk(data, p)[0], data["P_e"] - 2 * data["delta"])


def test_longer_parameter_vector_is_accepted_and_short_one_rejected(data):
    sk = compile_skeleton(SWING, variables=LIBRARY, n_outputs=3)
    np.testing.assert_allclose(sk(data, jnp.ones(MAX_PARAMS)), sk(data, jnp.ones(7)))
    with pytest.raises(ValueError, match="length >= 7"):
        sk(data, jnp.ones(3))
    with pytest.raises(ValueError, match="i_d"):
        sk({k: v for k, v in data.items() if k != "i_d"}, jnp.ones(7))


def test_docstring_annotations_and_unpacking():
    text = '''
    def f(delta: jnp.ndarray, omega: float, p: jax.Array) -> tuple[float, float]:
        """Docstrings are dropped."""
        a, b = delta * 2, omega
        c = d = a + b
        return c, d
    '''
    sk = compile_skeleton(text, variables=LIBRARY, n_outputs=2)
    assert '"""' not in sk.source and "jnp.ndarray" not in sk.source and "->" not in sk.source
    out = sk({"delta": jnp.array([1.0]), "omega": jnp.array([2.0])}, jnp.zeros(0))
    np.testing.assert_array_equal(out, [[4.0], [4.0]])


def test_counts():
    sk = compile_skeleton(
        "def f(omega, p):\n    return p[3] * omega ** 2 + 0.5 - jnp.pi\n",
        variables=LIBRARY,
        n_outputs=1,
    )
    assert sk.n_params == 4
    assert sk.n_constants == 2  # 2 and 0.5; the index 3 and pi are not counted
    # Return; 4 BinOps and their 4 operators; Subscript, Name p, Constant 3; Name omega;
    # Constants 2 and 0.5; Attribute and Name jnp
    assert sk.length == 1 + 4 + 4 + 3 + 1 + 2 + 2


# -- extraction ------------------------------------------------------------------------------


def test_extract_from_prose_and_fences_with_json_requests():
    answer = textwrap.dedent(
        """
        Sure! The rotor angle follows the swing equation; I think we also need the d-axis current.

        ```python
        import jax.numpy as jnp

        def equation(delta, omega, e_qp, P_m, P_e, i_d, p):
            d_delta = p[0] * (omega - 1.0)
            d_omega = p[1] * P_m + p[2] * P_e + p[3] * (omega - 1)
            d_eqp = p[4] * e_qp + p[5] * i_d + p[6]
            return d_delta, d_omega, d_eqp

        print(equation(1, 2, 3, 4, 5, 6, [0] * 7))
        ```

        Variables I would like:

        ```json
        {"variables": [{"name": "i_d", "role": "algebraic", "reason": "d-axis current"}]}
        ```
        """
    )
    source, requests = extract(answer)
    assert source.startswith("def equation(") and "print" not in source and "import" not in source
    assert requests == ({"name": "i_d", "role": "algebraic", "reason": "d-axis current"},)
    sk = compile_skeleton(answer, variables=LIBRARY, n_outputs=3)
    assert sk.requests == requests and sk.n_params == 7


def test_extract_picks_last_complete_function_or_named_one():
    answer = """
Draft:
```python
def equation(omega, p):
    return p[0] * omega
```
Better, with a helper (not used):
```python
def helper(omega):
    return omega

def equation(omega, P_m, p):
    return p[0] * omega + p[1] * P_m
```
"""
    source, _ = extract(answer)
    assert "P_m" in source
    assert extract(answer, "helper")[0].startswith("def helper(omega)")
    sk = compile_skeleton(answer, variables=LIBRARY, n_outputs=1)
    assert sk.arguments == ("omega", "P_m")
    with pytest.raises(SkeletonError, match="no function named 'missing'"):
        extract(answer, "missing")


def test_extract_skips_incomplete_trailing_function():
    answer = """
def equation(omega, p):
    return p[0] * omega

def equation(omega, p):
    return p[0] * (omega
"""
    source, _ = extract(answer)
    assert source == "def equation(omega, p):\n    return p[0] * omega\n"


def test_extract_nested_def_is_not_a_separate_candidate():
    text = """
def equation(omega, p):
    def inner(omega, p):
        return omega
    return inner(omega, p)
"""
    source, _ = extract(text)
    assert "inner" in source
    with pytest.raises(SkeletonError, match="nested function"):
        compile_skeleton(text, variables=LIBRARY, n_outputs=1)


@pytest.mark.parametrize(
    "text",
    [
        "    def f(omega, p):\n        return p[0] * omega\n",  # indented as a whole
        "def f(omega, p):\n\treturn p[0] * omega\n",  # tab
        "def f(omega, p):\n\ta = p[0]\n\treturn a * omega\n",
        "  def f(omega, p):\n \t  a = p[0]\n \t  return a * omega\n",  # mixed
        "def f(omega, p):\n\u00a0\u00a0\u00a0\u00a0return p[0] * omega\n",  # no-break spaces
        "def f(omega,\n      p):\n    return p[0] * omega\n",  # wrapped signature
        "def f(\n    omega, p\n):\n    return (p[0]\n* omega)\n",  # black style + continuation
        "Here it is: \n\ndef f(omega, p): return p[0] * omega\n\nThat is all.",
        "```py\ndef f(omega, p):\n    return p[0] * omega\n",  # unclosed fence
        "~~~python\ndef f(omega, p):\r\n    return p[0] * omega\r\n~~~\n",  # tildes, CRLF
    ],
)
def test_extract_odd_layouts(text):
    sk = compile_skeleton(text, variables=LIBRARY, n_outputs=1)
    out = sk({"omega": jnp.array([2.0])}, jnp.array([3.0]))
    np.testing.assert_array_equal(out, [[6.0]])


@pytest.mark.parametrize(
    ("tail", "expected"),
    [
        (
            '{"variables": [{"name": "i_d", "role": "algebraic"}]}',
            ({"name": "i_d", "role": "algebraic"},),
        ),
        ('[{"name": "i_q"}, {"name": "V_t"}]', ({"name": "i_q"}, {"name": "V_t"})),
        ('{\n  "variables": [\n    {"name": "i_q"}\n  ]\n}', ({"name": "i_q"},)),
        ('{"name": "i_q", "reason": "x"}', ({"name": "i_q", "reason": "x"},)),
        ('{"variables": ["i_q"]}', ({"name": "i_q"},)),
        ('```\n[{"name": "i_q"}]\n```', ({"name": "i_q"},)),
        ('{"variables": [{"name": "i_q"', ()),  # malformed: ignored
        ("```json\n{nope}\n```", ()),
        ('{"variables": 3}', ()),
        ("[" * 5000 + "]" * 5000, ()),  # too deep for json: ignored
        ('{"variables": [1, 2]} and then some prose', ()),  # not at the end
    ],
)
def test_trailing_json_requests(tail, expected):
    text = "```python\ndef f(omega, p):\n    return p[0] * omega\n```\n" + tail
    source, requests = extract(text)
    assert source.startswith("def f(omega, p)")
    assert requests == expected


def test_bare_function_then_bare_json():
    text = 'def f(omega, p):\n    return p[0] * omega\n\n{"variables": [{"name": "i_q"}]}\n'
    assert extract(text) == ("def f(omega, p):\n    return p[0] * omega\n", ({"name": "i_q"},))


@pytest.mark.parametrize("text", ["", "no code here", "```python\nx = 1\n```", "{}"])
def test_no_function(text):
    with pytest.raises(SkeletonError, match="no Python function"):
        extract(text)


# -- error messages --------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("body", "line", "fragment"),
    [
        ("    return open('x')\n", 2, "calls 'open', which is not an allowed math function"),
        ("    a = 1\n    return b\n", 3, "uses the name 'b'"),
        ("    return p[0] * omega, omega\n", 2, "returns 2 values but the task needs 1"),
        ("    return p * omega\n", 2, "uses p on its own"),
        ("    return p[-1]\n", 2, "integer literal index"),
        (f"    return p[{MAX_PARAMS}]\n", 2, f"p[0] ... p[{MAX_PARAMS - 1}]"),
        ("    return p[0.5]\n", 2, "integer literal index"),
        ("    return omega ** omega\n", 2, "exponents must be numbers"),
        ("    return omega ** 9\n", 2, "between -8 and 8"),
        ("    return omega ** (1 / 0)\n", 2, "between -8 and 8"),
        ("    return jnp.sin(omega, 1)\n", 2, "with 2 arguments; it takes 1"),
        ("    return jnp.sin(x=omega)\n", 2, "keyword arguments"),
        ("    return jnp.sin\n", 2, "without calling it"),
        ("    return omega // 2\n", 2, "operator '//'"),
        ("    return not omega\n", 2, "operator 'not'"),
        ("    return omega is None\n", 2, "comparison 'is'"),
        ("    return omega and 1\n", 2, "'and' and 'or'"),
        ("    return 2e6 * omega\n", 2, "too large"),
        ("    return True\n", 2, "only numbers"),
        ("    return 1j\n", 2, "complex"),
        ("    sin = 1\n    return sin\n", 2, "reserved"),
        ("    omega += 1\n    zz += 1\n    return omega\n", 3, "before it is assigned"),
        ("    a, b = omega\n    return a\n", 2, "unpacking"),
        ("    omega\n    return omega\n", 2, "bare expression"),
        ("    return omega\n    return omega\n", 2, "only one return"),
        ("    a = omega\n", 2, "must end with a return"),
        ("    return\n", 2, "returns nothing"),
        ("    return ()\n", 2, "empty tuple"),
        ("    if omega > 1:\n        omega = 1\n    return omega\n", 2, "if-statements"),
        ("    return omega[0]\n", 2, "only p[i] may be indexed"),
        ("    return omega.real\n", 2, "accesses the attribute omega.real"),
    ],
)
def test_rejections_name_line_and_reason(body, line, fragment):
    error = try_compile("def f(omega, p):\n" + body, variables=LIBRARY, n_outputs=1)
    assert isinstance(error, SkeletonError), error
    assert fragment in error.reason
    assert error.line == line
    assert str(error) == f"line {line}: {error.reason}"


def test_signature_rejections():
    cases = {
        "def f(omega, q):\n    return q\n": "last parameter must be the parameter vector p",
        "def f(omega, theta, psi, p):\n    return omega\n": "'theta', 'psi', which are not in",
        "def f(omega, p=1):\n    return omega\n": "default values",
        "def f(*omega, p):\n    return omega\n": "plain positional",
        "def f(omega, p, **kw):\n    return omega\n": "plain positional",
        "def f(omega, /, p):\n    return omega\n": "plain positional",
        "def f(omega, omega, p):\n    return omega\n": "repeated",
        "def _f(omega, p):\n    return omega\n": "names starting with _",
        "def f(omega: 'str', p):\n    return omega\n": "annotations",
    }
    for text, fragment in cases.items():
        error = try_compile(text, variables=LIBRARY, n_outputs=1)
        assert isinstance(error, SkeletonError) and fragment in error.reason, (text, error)
        assert error.line == 1


def test_check_returns_normalised_tree_and_validates_library():
    tree = check('def f(omega, p):\n    "doc"\n    return omega\n', variables=["omega"])
    assert len(tree.body) == 1
    for bad in (["p"], ["sin"], ["__x"], ["a b"], "omega"):
        with pytest.raises(SkeletonError):
            check("def f(p):\n    return p[0]\n", variables=bad)


def test_error_is_a_value_error_and_pickles():
    error = try_compile("def f(omega, p):\n    return open(1)\n", variables=LIBRARY, n_outputs=1)
    assert isinstance(error, ValueError)
    again = pickle.loads(pickle.dumps(error))
    assert (again.reason, again.line, str(again)) == (error.reason, error.line, str(error))
    assert str(SkeletonError("no line")) == "no line"


# -- probe -----------------------------------------------------------------------------------


def test_probe(data):
    sk = compile_skeleton(SWING, variables=LIBRARY, n_outputs=3)
    out = probe(sk, data, jax.random.key(0))
    assert out.shape == (3, 50) and jnp.isfinite(out).all()

    nan = compile_skeleton(
        "def f(omega, p):\n    return omega, jnp.log(-omega - p[0] ** 2)\n",
        variables=LIBRARY,
        n_outputs=2,
    )
    with pytest.raises(SkeletonError, match="output 2 is not finite"):
        probe(nan, data, jax.random.key(0))

    # log(p[0] * omega) is nan for p[0] < 0 but fine for some draws
    sometimes = compile_skeleton(
        "def f(omega, p):\n    return jnp.log(p[0] * omega)\n", variables=LIBRARY, n_outputs=1
    )
    assert probe(sometimes, data, jax.random.key(3), tries=10).shape == (1, 50)

    with pytest.raises(SkeletonError, match="evaluating the skeleton failed"):
        probe(sk, {"omega": data["omega"]}, jax.random.key(0))
    bad_shapes = {**data, "omega": jnp.ones(7)}
    with pytest.raises(SkeletonError, match="incompatible shapes"):
        probe(sk, bad_shapes, jax.random.key(0))


@pytest.mark.parametrize("name", ["lambda", "None", "class"])
def test_keywords_are_not_variables(name):
    error = try_compile(SWING, variables=[*LIBRARY, name], n_outputs=3)
    assert isinstance(error, SkeletonError) and "invalid name" in error.reason
