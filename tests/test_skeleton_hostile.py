"""Hostile skeletons: everything is rejected with a reason, and nothing of it ever runs.

Every hostile snippet carries a sentinel: a call to ``fire`` (installed in ``builtins`` during
the tests, so that any code that ran with ordinary builtins would reach it), a write to a
sentinel file, or an import. ``Watch`` also spies on ``compile`` (to code, not to a syntax
tree), ``exec``, ``eval``, ``open``, ``__import__`` and ``os.system``. For a rejected text none
of them may be called: the text never reached anything that could run it. Control tests run
the same snippets naively with ``exec`` to show that the sentinels are live.

The second half fuzzes ``compile_skeleton`` with hypothesis: random text, mutations of valid
skeletons and random syntax trees (including non-whitelisted nodes). The only outcomes are a
``Skeleton`` or a ``SkeletonError``; a tree with a non-whitelisted node is always rejected
without anything running; a whitelisted tree compiles and agrees with a naive evaluation.
"""

from __future__ import annotations

import ast
import builtins
import contextlib
import math
import os
import sys
import time
from pathlib import Path
from typing import Any

import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import jaxdmd  # noqa: F401  (enables float64)
from jaxdmd.skeleton import (
    MAX_DEPTH,
    MAX_PARAMS,
    MAX_SOURCE_CHARS,
    Skeleton,
    SkeletonError,
    compile_skeleton,
    try_compile,
)

VARIABLES = ("x", "y", "z")
SENTINEL = Path(os.environ.get("TMPDIR", "/tmp")) / f"jaxdmd-skeleton-sentinel-{os.getpid()}"


class Watch:
    """Record calls of fire() and of the builtins that can run or reach code, while active.

    The import system's own calls are not recorded: a module imported lazily for the first time
    in the process (which depends on the tests run before, and on the worker under
    pytest-xdist) is executed by ``importlib`` with ``exec``, from a frozen frame."""

    def __init__(self) -> None:
        self.events: list[str] = []
        self._saved: dict[str, Any] = {}

    def __enter__(self) -> Watch:
        real = {n: getattr(builtins, n) for n in ("compile", "exec", "eval", "open", "__import__")}
        self._saved = dict(real)
        self._saved["system"] = os.system
        events = self.events

        def importing() -> bool:  # called by the import system (frozen importlib)
            return sys._getframe(2).f_code.co_filename.startswith("<frozen ")

        def spy_compile(source, filename, mode, flags=0, *args, **kwargs):
            if not flags & ast.PyCF_ONLY_AST and not importing():  # ast.parse is fine
                events.append(f"compile {filename}")
            return real["compile"](source, filename, mode, flags, *args, **kwargs)

        def spy(name: str):
            def wrapper(*args, **kwargs):
                if not importing():
                    events.append(name)
                return real[name](*args, **kwargs)

            return wrapper

        def fire(*args):
            events.append("fire")
            return 1.0

        def spy_import(name, *args, **kwargs):
            # the standard library imports lazily (ast.walk imports collections on every call);
            # an import from code that was compiled from text has a file name like <string>
            caller = sys._getframe(1).f_code.co_filename
            if caller.startswith("<") and not caller.startswith("<frozen "):
                events.append(f"import {name}")
            return real["__import__"](name, *args, **kwargs)

        builtins.compile = spy_compile
        for name in ("exec", "eval", "open"):
            setattr(builtins, name, spy(name))
        builtins.__import__ = spy_import
        os.system = lambda *args: events.append("system") or 0
        builtins.fire = fire  # type: ignore[attr-defined]
        return self

    def __exit__(self, *exc: object) -> None:
        for name in ("compile", "exec", "eval", "open", "__import__"):
            setattr(builtins, name, self._saved[name])
        os.system = self._saved["system"]
        del builtins.fire  # type: ignore[attr-defined]


def compile_watched(text: str, n_outputs: int = 1, **kwargs: Any) -> tuple[Any, list[str]]:
    """try_compile under a Watch; returns the result and the recorded events."""
    SENTINEL.unlink(missing_ok=True)
    with Watch() as watch:
        result = try_compile(text, variables=VARIABLES, n_outputs=n_outputs, **kwargs)
    assert not SENTINEL.exists()
    return result, watch.events


def assert_rejected_silently(text: str, fragment: str = "", n_outputs: int = 1) -> SkeletonError:
    result, events = compile_watched(text, n_outputs)
    assert isinstance(result, SkeletonError), f"accepted:\n{text}"
    assert not result.reason.startswith("internal error"), result
    assert fragment in result.reason, (fragment, str(result))
    assert events == [], (events, text)
    return result


H = "def equation(x, y, p):\n"  # header of most snippets

# (id, code, live): live snippets fire their sentinel when run naively (see the control test);
# the others would hang, exhaust memory or do nothing observable.
CORPUS: list[tuple[str, str, str, bool]] = [
    ("import", H + "    import builtins\n    builtins.fire()\n    return x\n", "import", True),
    ("from-import", H + "    from builtins import fire\n    return fire()\n", "import", True),
    ("dunder-import", H + "    return __import__('builtins').fire()\n", "dunder", True),
    ("getattr", H + "    return getattr(x, 'real', fire())\n", "calls 'getattr'", True),
    ("globals", H + "    return globals()['__builtins__']\n", "only p[i]", False),
    ("vars", H + "    return vars()\n", "calls 'vars'", False),
    ("class-bases", H + "    return ().__class__.__bases__[0].__subclasses__()\n", "", False),
    (
        "class-escape",
        H + "    return [c for c in ().__class__.__base__.__subclasses__()"
        " if c.__name__ == 'catch_warnings'][0]()._module.__builtins__['fire']()\n",
        "dunder",
        True,
    ),
    ("open", H + f"    return open('{SENTINEL}', 'w').write('x')\n", "not an allowed math", True),
    ("open-homoglyph", H + f"    return \uff4fpen('{SENTINEL}', 'w')\n", "calls 'open'", True),
    ("eval", H + '    return eval("fire()")\n', "calls 'eval'", True),
    ("exec", H + '    exec("fire()")\n    return x\n', "calls 'exec'", True),
    ("compile", H + "    return compile('fire()', 'f', 'eval')\n", "calls 'compile'", False),
    ("os-system", H + "    return jnp.os.system('true')\n", "not an allowed math", False),
    ("print", H + "    return print(fire())\n", "calls 'print'", True),
    ("breakpoint", H + "    return breakpoint()\n", "calls 'breakpoint'", False),
    ("while", H + "    while True:\n        pass\n    return x\n", "loops", False),
    ("for", H + "    for i in range(3):\n        fire()\n    return x\n", "loops", True),
    ("listcomp", H + "    return sum([fire() for i in range(2)])\n", "calls 'sum'", True),
    ("listcomp-bare", H + "    return [fire() for i in range(2)][0]\n", "only p[i]", True),
    ("genexp", H + "    a = (fire() for i in (1,))\n    return x\n", "generator", False),
    ("dictcomp", H + "    a = {i: fire() for i in (1,)}\n    return x\n", "comprehension", False),
    ("pow-chain", H + "    return x ** 10 ** 10\n", "chain of powers", False),
    ("pow-tower", H + "    return 9 ** 9 ** 9\n", "chain of powers", False),
    ("pow-huge", H + "    return x ** 100000000\n", "too large", False),
    ("pow-variable", H + "    return x ** y\n", "exponents must be", False),
    ("pow-nested-const", H + "    return x ** (2 * (3 ** 5))\n", "chain of powers", False),
    ("giant-int", H + "    return x * 12345678901234567890123\n", "too large", False),
    ("giant-float", H + "    return x * 1e300\n", "too large", False),
    ("inf-literal", H + "    return x * 1e999\n", "too large", False),
    ("recursion", H + "    return fire() + equation(x, y, p)\n", "calls 'fire'", True),
    ("recursion-only", H + "    return equation(x, y, p)\n", "calls 'equation'", False),
    ("long", H + "    return " + " + ".join(["x"] * 2000) + "\n", "characters long", False),
    ("wide-sum", H + "    return " + "+".join(["x"] * 700) + "\n", "nested too deeply", False),
    ("many-nodes", H + "    a = x + y * x\n" * 90 + "    return a\n", "600", False),
    ("deep-parens", H + "    return " + "(" * 300 + "x" + ")" * 300 + "\n", "not valid", False),
    ("deep-parens-2", H + "    return " + "(x+" * 100 + "x" + ")" * 100 + "\n", "nested", False),
    ("deep-unary", H + "    return " + "-" * 3900 + "x\n", "nested too deeply", False),
    ("deep-calls", H + "    return " + "sin(" * 60 + "x" + ")" * 60 + "\n", "nested", False),
    ("lambda", H + "    f = lambda: fire()\n    return f()\n", "lambda", True),
    ("lambda-call", H + "    return (lambda: fire())()\n", "lambda", True),
    ("nested-def", H + "    def g():\n        return fire()\n    return g()\n", "nested", True),
    ("decorator", "@fire\n" + H + "    return x\n", "decorators", True),
    ("default", "def equation(x, y, p=fire()):\n    return x\n", "default", True),
    ("annotation", "def equation(x: fire(), y, p):\n    return x\n", "annotations", True),
    ("return-annotation", "def equation(x, y, p) -> fire():\n    return x\n", "annot", True),
    ("kwonly", "def equation(x, *, p=fire()):\n    return x\n", "positional", True),
    ("global", H + "    global FLAG\n    FLAG = fire()\n    return x\n", "global", True),
    ("nonlocal", H + "    nonlocal FLAG\n    return x\n", "nonlocal", False),
    ("p-attribute", H + "    return p.__class__\n", "dunder", False),
    ("p-index-attr", H + "    return p[0].__class__.__mro__\n", "dunder", False),
    ("jnp-dunder", H + "    return jnp.sin.__globals__['fire']()\n", "dunder", False),
    ("jnp-other", H + "    return jnp.load('x')\n", "not an allowed math function", False),
    ("string", H + "    s = 'import os'\n    return x\n", "strings", False),
    ("bytes", H + "    s = b'x'\n    return x\n", "strings", False),
    ("fstring", H + '    s = f"{fire()}"\n    return x\n', "f-strings", True),
    ("walrus", H + "    return (q := fire())\n", "walrus", True),
    ("keyword", H + "    return jnp.sin(x, out=fire())\n", "keyword", True),
    ("starred", H + "    return jnp.sin(*[fire()])\n", "*arguments", True),
    (
        "try",
        H + "    try:\n        fire()\n    except Exception:\n        pass\n    return x\n",
        "try",
        True,
    ),
    ("with", H + "    with open('f') as f:\n        pass\n    return x\n", "with", False),
    ("class", H + "    class A:\n        fire()\n    return x\n", "class", True),
    ("yield", H + "    yield fire()\n    return x\n", "yield", False),
    ("await", "async def equation(x, y, p):\n    return await fire()\n", "async", False),
    ("del", H + "    del x\n    return y\n", "del", False),
    ("assert", H + "    assert fire()\n    return x\n", "assert", True),
    ("raise", H + "    raise SystemExit(fire())\n", "raise", True),
    ("if-statement", H + "    if fire():\n        pass\n    return x\n", "if-statements", True),
    ("subscript-assign", H + "    p[0] = fire()\n    return x\n", "calls 'fire'", True),
    ("attr-assign", H + "    x.y = 1\n    return x\n", "only simple local names", False),
    ("shadow", H + "    sin = fire\n    return sin(x)\n", "name 'fire'", False),
    ("shadow-pi", H + "    pi = fire()\n    return x\n", "calls 'fire'", True),
    ("bool-op", H + "    return y and fire()\n", "'and' and 'or'", True),
    ("dunder-name", H + "    return __builtins__\n", "dunder", False),
    ("unknown-arg", "def equation(x, os, p):\n    return x\n", "'os', which is not in", False),
    ("two-functions", H + "    return x\n" + H + "    return fire()\n", "calls 'fire'", True),
    ("null-byte", H + "    return x\x00\n", "", False),
    (
        "match",
        H + "    match x:\n        case 1:\n            fire()\n    return x\n",
        "match",
        True,
    ),
    ("ellipsis", H + "    return ...\n", "only numbers", False),
    ("none", H + "    return None\n", "only numbers", False),
]


@pytest.mark.parametrize(("code", "fragment"), [c[1:3] for c in CORPUS], ids=[c[0] for c in CORPUS])
def test_hostile_snippet_is_rejected_and_nothing_runs(code, fragment):
    error = assert_rejected_silently(code, fragment)
    assert str(error).startswith(f"line {error.line}: ") or error.line is None


@pytest.mark.parametrize("code", [c[1] for c in CORPUS if c[3]], ids=[c[0] for c in CORPUS if c[3]])
def test_control_hostile_snippets_are_live_when_run_naively(code):
    """Run naively, each live snippet fires its sentinel: the rejection tests mean something."""
    namespace: dict[str, Any] = {"jnp": jnp, "np": np, "math": math}
    SENTINEL.unlink(missing_ok=True)
    with Watch() as watch:
        try:
            # defines `equation`; decorators, defaults and annotations fire already here
            exec(compile(code, "<string>", "exec", dont_inherit=True), namespace)
            namespace["equation"](1.0, 2.0, [0.5, 0.5])
        except BaseException:  # raise SystemExit(...) is one of the snippets
            pass
    fired = "fire" in watch.events or SENTINEL.exists()
    SENTINEL.unlink(missing_ok=True)
    assert fired


def test_module_level_code_around_the_function_never_runs():
    text = f"""Here you go:
```python
import os
fire()
open('{SENTINEL}', 'w')
def equation(x, y, p):
    return p[0] * x
fire()
os.system('touch {SENTINEL}')
```
"""
    result, events = compile_watched(text)
    assert isinstance(result, Skeleton)
    assert "fire" not in events and "open" not in events and "system" not in events
    assert "import" not in result.source and "fire" not in result.source
    assert events.count("exec") == 1  # the def of the checked function, nothing else
    with Watch() as watch:
        out = result({"x": jnp.ones(3), "y": jnp.ones(3)}, jnp.array([2.0]))
    assert watch.events == [] and out.shape == (1, 3)


def test_compiled_function_has_no_builtins_and_no_attribute_escape():
    text = "def f(x, p):\n    return p[0] * jnp.sin(x) + 2.0 * pi\n"
    sk = compile_skeleton(text, variables=VARIABLES, n_outputs=1)
    assert sk.fn.__globals__["__builtins__"] == {}
    names = set(sk.fn.__globals__) - {"__builtins__", "f"}
    assert all(n.startswith(("_m_", "_k")) for n in names)
    assert set(sk.fn.__code__.co_names) == {"_m_sin", "_m_pi", "_k0"}


def test_non_text_inputs():
    for bad in (None, b"def f(p): return p[0]", 3, ["def f(p): return p[0]"]):
        result, events = compile_watched(bad)  # type: ignore[arg-type]
        assert isinstance(result, SkeletonError) and events == []
    result, _ = compile_watched("x" * 200_000)
    assert isinstance(result, SkeletonError) and "characters" in result.reason


# -- fuzzing ---------------------------------------------------------------------------------

VALID = [
    "def equation(x, y, p):\n    a = p[0] * (x - 1.0)\n    return a + p[1] * y ** 2\n",
    "def equation(x, y, z, p):\n    d = p[0] * jnp.sin(x - y) + p[1]\n"
    "    return d, p[2] * z if x > 0.5 else -z\n",
    "```python\ndef f(y, p):\n    return jnp.where(y > p[0], y, p[1]) * math.pi\n```\n"
    '{"variables": [{"name": "i_d"}]}',
]
FRAGMENTS = [
    "__import__('os')",
    "fire()",
    "open('f')",
    "().__class__",
    "import os\n",
    "\n    while 1:\n",
    "lambda: 0",
    " ** 10 ** 10",
    "9**9**9",
    "[i for i in x]",
    "p.__class__",
    "'s'",
    "f'{x}'",
    "(q := 1)",
    "eval",
    "exec",
    "getattr",
    "@fire\n",
    "global g\n",
    "\t",
    "\n",
    "(",
    ")",
    ":",
    "p[",
    "]",
    "**",
    "#",
    '"""',
    "```",
    "{",
    "\x00",
    "def g(p):\n",
    "return",
    "1e999",
    "-",
]
settings_fuzz = settings(
    max_examples=150,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
    derandomize=True,
)


def outcome(text: str, n_outputs: int = 1) -> Skeleton | SkeletonError:
    """The only outcomes allowed: a Skeleton or a non-internal SkeletonError, quickly."""
    start = time.perf_counter()
    result, events = compile_watched(text, n_outputs)
    assert time.perf_counter() - start < 10.0
    assert isinstance(result, Skeleton | SkeletonError)
    assert "fire" not in events and "open" not in events and "system" not in events
    if isinstance(result, SkeletonError):
        assert not result.reason.startswith("internal error"), result
        assert events == []
    return result


@settings_fuzz
@given(st.text(max_size=400))
def test_fuzz_random_text(text):
    outcome(text)


@settings_fuzz
@given(
    st.lists(
        st.sampled_from([*FRAGMENTS, "def equation(x, p):", " x", " y", "p[0]", "    ", "+"]),
        max_size=40,
    ).map("".join)
)
def test_fuzz_random_tokens(text):
    outcome(text)


@settings_fuzz
@given(
    base=st.sampled_from(VALID),
    edits=st.lists(
        st.tuples(
            st.sampled_from(["insert", "delete", "replace", "duplicate"]),
            st.integers(0, 10_000),
            st.integers(1, 12),
            st.sampled_from(FRAGMENTS) | st.text(max_size=3),
        ),
        min_size=1,
        max_size=4,
    ),
)
def test_fuzz_mutated_valid_skeletons(base, edits):
    text = base
    for kind, position, length, fragment in edits:
        i = position % (len(text) + 1)
        if kind == "insert":
            text = text[:i] + fragment + text[i:]
        elif kind == "delete":
            text = text[:i] + text[i + length :]
        elif kind == "replace":
            text = text[:i] + fragment + text[i + length :]
        else:
            text = text[:i] + text[i : i + length] * 2 + text[i + length :]
    result = outcome(text, n_outputs=2 if "d, p[2]" in base else 1)
    if isinstance(result, Skeleton):
        data = {name: jnp.linspace(0.1, 1.0, 4) for name in VARIABLES}
        # a mutation may ask for a variable that is not in the data
        with Watch() as watch, contextlib.suppress(ValueError):
            result(data, jnp.ones(MAX_PARAMS))
        assert watch.events == []


# Random syntax trees. Each strategy draws (node, hostile): hostile means the tree contains a
# construct outside the whitelist.

Load = ast.Load


def _name(n: str) -> ast.Name:
    return ast.Name(id=n, ctx=Load())


def _call(func: ast.expr, *args: ast.expr) -> ast.Call:
    return ast.Call(func=func, args=list(args), keywords=[])


def _param(i: int) -> ast.Subscript:
    return ast.Subscript(value=_name("p"), slice=ast.Constant(i), ctx=Load())


def _attr(base: str, attr: str) -> ast.Attribute:
    return ast.Attribute(value=_name(base), attr=attr, ctx=Load())


safe_leaves = st.one_of(
    st.sampled_from(VARIABLES).map(_name),
    st.integers(0, 5).map(_param),
    st.floats(0.0, 1000.0).map(ast.Constant),
    st.just(_name("pi")),
    st.sampled_from(["jnp", "np", "math"]).map(lambda ns: _attr(ns, "pi")),
).map(lambda node: (node, False))

hostile_leaves = st.sampled_from(
    [
        _call(_name("fire")),
        _call(_name("open"), ast.Constant(str(SENTINEL)), ast.Constant("w")),
        _call(_name("__import__"), ast.Constant("os")),
        _call(_name("eval"), ast.Constant("fire()")),
        _call(_name("getattr"), _name("x"), ast.Constant("real")),
        ast.Attribute(value=_name("p"), attr="__class__", ctx=Load()),
        _attr("jnp", "load"),
        ast.Constant("text"),
        ast.Constant(b"bytes"),
        ast.Constant(True),
        ast.Constant(None),
        ast.Constant(1e300),
        ast.Constant(10**30),
        ast.Constant(2j),
        _name("__builtins__"),
        _name("undefined"),
        _name("p"),
        ast.Subscript(value=_name("p"), slice=ast.Constant(-1), ctx=Load()),
        ast.Subscript(value=_name("p"), slice=ast.Constant(99), ctx=Load()),
        ast.Subscript(value=_name("x"), slice=ast.Constant(0), ctx=Load()),
        ast.Lambda(
            args=ast.arguments(posonlyargs=[], args=[], kwonlyargs=[], kw_defaults=[], defaults=[]),
            body=_call(_name("fire")),
        ),
        ast.JoinedStr(values=[ast.FormattedValue(value=_call(_name("fire")), conversion=-1)]),
    ]
).map(lambda node: (node, True))

SAFE_BINOPS = [ast.Add(), ast.Sub(), ast.Mult(), ast.Div()]
HOSTILE_BINOPS = [ast.FloorDiv(), ast.Mod(), ast.BitXor(), ast.MatMult(), ast.LShift()]
SAFE_CMPS = [ast.Lt(), ast.LtE(), ast.Gt(), ast.GtE(), ast.Eq(), ast.NotEq()]
HOSTILE_CMPS = [ast.Is(), ast.In(), ast.NotIn()]
SAFE_FUNCTIONS = {
    "sin": 1,
    "exp": 1,
    "tanh": 1,
    "abs": 1,
    "sqrt": 1,
    "arctan2": 2,
    "atan": 1,
    "maximum": 2,
    "minimum": 2,
    "where": 3,
    "clip": 3,
    "square": 1,
    "sign": 1,
}
SAFE_EXPONENTS = [
    *[ast.Constant(k) for k in (2, 3, 8, 0.5)],
    ast.UnaryOp(op=ast.USub(), operand=ast.Constant(2)),
    ast.BinOp(left=ast.Constant(1), op=ast.Div(), right=ast.Constant(3)),
    _param(0),
    ast.UnaryOp(op=ast.USub(), operand=_param(1)),
]
HOSTILE_EXPONENTS = [
    ast.Constant(9),
    ast.Constant(1e6),
    _name("x"),
    ast.BinOp(left=ast.Constant(10), op=ast.Pow(), right=ast.Constant(10)),
    ast.BinOp(left=_param(0), op=ast.Mult(), right=ast.Constant(2)),
]


def _extend(children):
    pair = st.tuples(children, children)

    def binop(ab, op):
        (a, ha), (b, hb) = ab
        return ast.BinOp(left=a, op=op, right=b), ha or hb or type(op) in map(type, HOSTILE_BINOPS)

    def power(base, exponent, hostile):
        return ast.BinOp(left=base[0], op=ast.Pow(), right=exponent), base[1] or hostile

    def call(name, namespace, args):
        func = _name(name) if namespace is None else _attr(namespace, name)
        nodes = [a for a, _ in args]
        hostile = any(h for _, h in args) or len(args) != SAFE_FUNCTIONS[name]
        return _call(func, *nodes), hostile

    def compare(items, ops):
        (first, h0), *rest = items
        ops = ops[: len(rest)]
        hostile = (
            h0 or any(h for _, h in rest) or any(type(o) in map(type, HOSTILE_CMPS) for o in ops)
        )
        return ast.Compare(left=first, ops=ops, comparators=[c for c, _ in rest]), hostile

    def wrap(kind, child):
        node, hostile = child
        if kind == "neg":
            return ast.UnaryOp(op=ast.USub(), operand=node), hostile
        if kind == "not":
            return ast.UnaryOp(op=ast.Not(), operand=node), True
        if kind == "invert":
            return ast.UnaryOp(op=ast.Invert(), operand=node), True
        if kind == "attr":
            return ast.Attribute(value=node, attr="real", ctx=Load()), True
        if kind == "slice":
            return ast.Subscript(value=node, slice=ast.Slice(), ctx=Load()), True
        if kind == "walrus":
            return ast.NamedExpr(target=ast.Name(id="w", ctx=ast.Store()), value=node), True
        if kind == "listcomp":
            gen = ast.comprehension(
                target=ast.Name(id="i", ctx=ast.Store()),
                iter=_call(_name("range"), ast.Constant(2)),
                ifs=[],
                is_async=0,
            )
            return ast.ListComp(elt=node, generators=[gen]), True
        if kind == "tuple":
            return ast.Tuple(elts=[node, node], ctx=Load()), True
        if kind == "starred":
            return _call(_name("sin"), ast.Starred(value=node, ctx=Load())), True
        if kind == "keyword":
            return ast.Call(
                func=_name("sin"), args=[node], keywords=[ast.keyword(arg="out", value=node)]
            ), True
        if kind == "boolop":
            return ast.BoolOp(op=ast.Or(), values=[node, node]), True
        if kind == "yield":
            return ast.Yield(value=node), True
        if kind == "hostile-call":
            return _call(_name("fire"), node), True
        return _call(ast.Attribute(value=node, attr="__class__", ctx=Load())), True

    safe = st.one_of(
        st.builds(binop, pair, st.sampled_from(SAFE_BINOPS)),
        st.builds(power, children, st.sampled_from(SAFE_EXPONENTS), st.just(False)),
        st.builds(
            call,
            st.sampled_from(sorted(SAFE_FUNCTIONS)),
            st.sampled_from([None, "jnp", "np", "math"]),
            st.lists(children, min_size=1, max_size=3),
        ),
        st.builds(
            compare,
            st.lists(children, min_size=2, max_size=3),
            st.lists(st.sampled_from(SAFE_CMPS), min_size=2, max_size=2),
        ),
        st.builds(
            lambda t, b, o: (
                ast.IfExp(test=t[0], body=b[0], orelse=o[0]),
                t[1] or b[1] or o[1],
            ),
            children,
            children,
            children,
        ),
        st.builds(wrap, st.just("neg"), children),
    )
    hostile = st.one_of(
        st.builds(binop, pair, st.sampled_from(HOSTILE_BINOPS)),
        st.builds(power, children, st.sampled_from(HOSTILE_EXPONENTS), st.just(True)),
        st.builds(
            compare,
            st.lists(children, min_size=2, max_size=2),
            st.lists(st.sampled_from(HOSTILE_CMPS), min_size=1, max_size=1),
        ),
        st.builds(
            wrap,
            st.sampled_from(
                [
                    "not",
                    "invert",
                    "attr",
                    "slice",
                    "walrus",
                    "listcomp",
                    "tuple",
                    "starred",
                    "keyword",
                    "boolop",
                    "yield",
                    "hostile-call",
                    "dunder-call",
                ]
            ),
            children,
        ),
    )
    return st.one_of(safe, safe, safe, hostile)


# Built once: hypothesis validates a strategy the first time it is drawn from.
EXPRESSIONS = {
    True: st.recursive(st.one_of(safe_leaves, hostile_leaves), _extend, max_leaves=10),
    False: st.recursive(safe_leaves, _extend, max_leaves=10).filter(lambda pair: not pair[1]),
}


HOSTILE_STATEMENTS = [
    ast.parse(code).body[0]
    for code in [
        "import os",
        "from os import system",
        "for i in range(2):\n    fire()",
        "while True:\n    pass",
        "if x:\n    fire()",
        "fire()",
        "global g",
        "try:\n    fire()\nexcept Exception:\n    pass",
        "with open('f') as h:\n    pass",
        "del x",
        "assert fire()",
        "raise ValueError",
        "def g():\n    return fire()",
        "class A:\n    pass",
        "p[0] = 1.0",
        "x.attr = 1.0",
        "a9: float = 1.0",
        "a9 = b9 = fire()",
        "x //= 2",
        "pass",
        "return fire()",
    ]
]


@st.composite
def functions(draw, allow_hostile: bool) -> tuple[str, int, bool]:
    """A random function: (source, number of outputs, contains a non-whitelisted construct)."""
    hostile = False
    body: list[ast.stmt] = []
    locals_: list[str] = []
    for k in range(draw(st.integers(0, 3))):
        value, h = draw(EXPRESSIONS[allow_hostile])
        hostile |= h
        if draw(st.booleans()) and locals_:
            target = draw(st.sampled_from(locals_))
            body.append(
                ast.AugAssign(
                    target=ast.Name(id=target, ctx=ast.Store()), op=ast.Mult(), value=value
                )
            )
        else:
            body.append(ast.Assign(targets=[ast.Name(id=f"a{k}", ctx=ast.Store())], value=value))
            locals_.append(f"a{k}")
        if allow_hostile and draw(st.integers(0, 5)) == 0:
            body.append(draw(st.sampled_from(HOSTILE_STATEMENTS)))
            hostile = True
    n_outputs = draw(st.integers(1, 3))
    outputs = []
    for _ in range(n_outputs):
        if locals_ and draw(st.booleans()):
            outputs.append(_name(draw(st.sampled_from(locals_))))
        else:
            value, h = draw(EXPRESSIONS[allow_hostile])
            hostile |= h
            outputs.append(value)
    value = outputs[0] if n_outputs == 1 else ast.Tuple(elts=outputs, ctx=Load())
    body.append(ast.Return(value=value))
    args = [ast.arg(arg=n) for n in VARIABLES] + [ast.arg(arg="p")]
    arguments = ast.arguments(posonlyargs=[], args=args, kwonlyargs=[], kw_defaults=[], defaults=[])
    decorators: list[ast.expr] = []
    if allow_hostile:
        trick = draw(st.integers(0, 12))
        hostile |= trick < 6
        if trick == 0:
            decorators = [_name("fire")]
        elif trick == 1:
            arguments.defaults = [_call(_name("fire"))]
        elif trick == 2:
            args[0].annotation = _call(_name("fire"))
        elif trick == 3:
            arguments.vararg = ast.arg(arg="rest")
        elif trick == 4:
            args[-1].arg = "q"
        elif trick == 5:
            args[0].arg = "os"
    fdef = ast.FunctionDef(
        name="equation", args=arguments, body=body, decorator_list=decorators, returns=None
    )
    module = ast.fix_missing_locations(ast.Module(body=[fdef], type_ignores=[]))
    return ast.unparse(module), n_outputs, hostile


def reference(source: str, data: dict, p) -> list:
    """Evaluate the checked source naively, with literals as float arrays, like the compiler."""
    tree = ast.parse(source)

    class Literals(ast.NodeTransformer):
        def visit_Subscript(self, node):
            return node

        def visit_BinOp(self, node):
            node.left = self.visit(node.left)
            if not isinstance(node.op, ast.Pow):
                node.right = self.visit(node.right)
            return node

        def visit_Constant(self, node):
            return _call(_name("asarray"), node)

    tree = ast.fix_missing_locations(Literals().visit(tree))
    namespace = {
        "jnp": jnp,
        "np": jnp,
        "math": jnp,
        "pi": jnp.pi,
        "asarray": lambda v: jnp.asarray(float(v)),
        "sin": jnp.sin,
        "exp": jnp.exp,
        "tanh": jnp.tanh,
        "abs": jnp.abs,
        "sqrt": jnp.sqrt,
        "arctan2": jnp.arctan2,
        "atan": jnp.arctan,
        "maximum": jnp.maximum,
        "minimum": jnp.minimum,
        "where": jnp.where,
        "clip": jnp.clip,
        "square": jnp.square,
        "sign": jnp.sign,
    }
    jnp.atan = jnp.arctan if not hasattr(jnp, "atan") else jnp.atan
    exec(compile(tree, "<reference>", "exec"), namespace)
    out = namespace["equation"](*(data[n] for n in VARIABLES), p)
    return list(out) if isinstance(out, tuple) else [out]


@settings(
    max_examples=120,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much],
)
@given(functions(allow_hostile=True))
def test_fuzz_syntax_trees(drawn):
    source, n_outputs, hostile = drawn
    result = outcome(source, n_outputs)
    if hostile:
        assert isinstance(result, SkeletonError), source


@settings(
    max_examples=60,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much],
)
@given(functions(allow_hostile=False))
def test_fuzz_whitelisted_trees_compile_and_match_naive_evaluation(drawn):
    source, n_outputs, hostile = drawn
    assert not hostile
    result = outcome(source, n_outputs)
    assert isinstance(result, Skeleton), (str(result), source)
    data = {"x": jnp.array([0.3, -1.7]), "y": jnp.array([2.5, 0.0]), "z": jnp.array([-0.5, 4.0])}
    p = jnp.linspace(-1.5, 2.0, 6)
    with Watch() as watch:
        out = result(data, p)
    assert watch.events == []
    assert out.shape == (n_outputs, 2)
    for i in range(2):  # sample by sample: `a if c else b` needs a single truth value
        sample = {name: values[i : i + 1] for name, values in data.items()}
        expected = reference(result.source, sample, p)
        for got, want in zip(out[:, i], expected, strict=True):
            np.testing.assert_allclose(got, jnp.ravel(want)[0], rtol=1e-12, equal_nan=True)


def test_depth_limit_is_below_python_recursion_limits():
    depth = MAX_DEPTH + 5
    text = "def equation(x, p):\n    return " + "sin(" * depth + "x" + ")" * depth + "\n"
    assert len(text) < MAX_SOURCE_CHARS
    assert_rejected_silently(text, "nested too deeply")
