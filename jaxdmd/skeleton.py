"""Skeletons: untrusted model text -> checked source -> pure JAX function.

A skeleton is a small Python function, written by a language model or by the offline proposer,
whose last parameter is a trainable parameter vector ``p``::

    def equation(delta, omega, e_qp, P_m, P_e, i_d, p):
        d_delta = p[0] * (omega - 1.0)
        d_omega = p[1] * P_m + p[2] * P_e + p[3] * (omega - 1)
        d_eqp = p[4] * e_qp + p[5] * i_d + p[6]
        return d_delta, d_omega, d_eqp

The text is untrusted. It is parsed (``ast.parse`` never runs code) and its syntax tree is checked
against a whitelist before anything is compiled; only then is a rewritten copy of the tree
compiled, in a namespace whose ``__builtins__`` is empty and whose only other names are the
allowed math functions and the skeleton's numeric constants.

What a skeleton may contain (everything else is rejected with the line and a reason):

- Exactly one ``def`` with plain positional parameters: variables from the caller's variable
  library, in any order, followed by ``p``. No defaults, ``*args``, ``**kwargs``, keyword-only or
  positional-only parameters, decorators or ``async``. Annotations are allowed only as plain
  (dotted, subscripted) names such as ``float`` or ``jnp.ndarray`` and are dropped unread. A
  leading docstring is allowed and dropped.
- Statements: assignments to simple local names (also ``a, b = x, y`` with a tuple of the same
  length), augmented assignments (``x += ...``) to defined names, and exactly one ``return`` of
  an expression or a tuple of expressions, as the last statement. There are no ``if``, loops,
  ``try``, ``with``, imports, ``global``, ``del``, ``assert``, nested ``def``/``class`` etc.
- Expressions: ``+ - * / **``, unary ``+ -``, comparisons ``< <= > >= == !=`` (chains allowed),
  conditional expressions ``a if c else b``, names that are parameters or earlier assignments,
  ``p[i]`` with ``i`` a non-negative integer literal below ``MAX_PARAMS``, numeric literals with
  ``|value| <= MAX_LITERAL`` (no strings, bytes, f-strings, booleans, ``None``, complex numbers),
  the constant ``pi`` (bare or as ``jnp.pi``/``np.pi``/``math.pi``) and ``e`` as ``jnp.e`` etc.
- Calls only to the math functions in ``FUNCTIONS`` (and the aliases in ``ALIASES``), bare or
  through one of the namespaces ``jnp``, ``np``, ``numpy``, ``math``, ``jax.numpy`` (which one is
  irrelevant: all resolve to ``jax.numpy``), with the right number of positional arguments.
- Exponents: a constant built from numeric literals with ``+ - * /`` (such as ``2``, ``-1`` or
  ``(1 / 3)``) whose value lies in ``[-MAX_EXPONENT, MAX_EXPONENT]``, or a parameter ``p[i]``
  (optionally negated), which the fitter can train. Anything else (a variable, an expression, a
  power chain like ``x ** 10 ** 10``) is rejected: a variable exponent makes the search space
  explode for little physical gain, and a constant one bounds the work.
- No name or attribute anywhere may start with an underscore (so no dunder names), and locals may
  not shadow ``p``, the math names or the namespaces.
- Size limits: ``MAX_SOURCE_CHARS`` characters, ``MAX_NODES`` syntax-tree nodes, ``MAX_DEPTH``
  levels of nesting (checked iteratively, before any recursive pass), ``MAX_PARAMS`` parameters;
  the number of returned values must equal the task's number of outputs.

Compilation rewrites the checked tree: math names become private globals bound to ``jax.numpy``
functions (``jnp.sin`` -> ``_m_sin``), numeric literals become float arrays (so that no Python
integer or float arithmetic, hence no ``ZeroDivisionError``/``OverflowError`` or big-integer
blow-up, can happen), exponents are folded to Python numbers, ``a if c else b`` becomes
``jnp.where(c, a, b)`` (both branches are evaluated), comparison chains become
``jnp.logical_and`` of pairs (each operand still evaluated once: a compound middle operand is bound
to a temporary) and comparisons become floats (0.0 or 1.0, so that ``-(a < b)`` works as in
Python), so that the function is pure and can be jitted, vmapped and differentiated. The
rewritten tree (``MAX_COMPILED_NODES``) and the interpreter's program (``interp.MAX_SSA``,
``interp.MAX_INSTRUCTIONS``) have size budgets, checked after each transformation: compiling
and evaluating a candidate costs at most a constant times its source (see ``sizes``).
Code around the function in the answer (imports, calls, prints) is never compiled.

Line numbers in errors count from the ``def`` line of the extracted function (line 1).
"""

from __future__ import annotations

import ast
import copy
import json
import keyword
import math
import re
import textwrap
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxdmd import interp, whitelist
from jaxdmd.whitelist import ALIASES, FUNCTIONS, MAX_PARAMS

__all__ = [
    "ALIASES",
    "FUNCTIONS",
    "Skeleton",
    "SkeletonError",
    "check",
    "compile_skeleton",
    "extract",
    "probe",
    "sizes",
    "try_compile",
]

MAX_ANSWER_CHARS = 100_000  # a whole model answer
MAX_SOURCE_CHARS = 4_000  # the extracted function
MAX_NODES = 600  # syntax-tree nodes of the function, without Load/Store markers
MAX_DEPTH = 50  # nesting of the syntax tree, counted from the module
MAX_LITERAL = 1e6  # largest magnitude of a numeric literal
MAX_EXPONENT = 8  # largest magnitude of a constant exponent
# Budgets after each transformation, so that compiling and evaluating a candidate cost at most a
# constant times its (checked, bounded) size. The rewrite adds a fixed number of nodes per node
# (a comparison pair: the call to logical_and, a temporary for a shared operand, the float
# conversion), and lowering emits a bounded number of instructions per node (an integer power
# at most 2 log2(MAX_EXPONENT) + 1); the measured worst cases lie far below these limits.
MAX_COMPILED_NODES = 8 * MAX_NODES  # nodes of the rewritten tree that is compiled
MAX_PROGRAM_INSTRUCTIONS = interp.MAX_INSTRUCTIONS  # instructions of the lowered program

# The vocabulary (FUNCTIONS, ALIASES, constants, namespaces, reserved names) lives in
# jaxdmd.whitelist, which jaxdmd.interp reads too.
_CONSTANTS = whitelist.CONSTANTS
_BARE_CONSTANTS = whitelist.BARE_CONSTANTS
_NAMESPACES = whitelist.NAMESPACES
_RESERVED = whitelist.RESERVED
_math_name = whitelist.math_name
_is_param = whitelist.is_param
_fold = whitelist.fold

_OPERATORS: dict[type, str] = {
    ast.Add: "+",
    ast.Sub: "-",
    ast.Mult: "*",
    ast.Div: "/",
    ast.Pow: "**",
}
_COMPARISONS = (ast.Lt, ast.LtE, ast.Gt, ast.GtE, ast.Eq, ast.NotEq)
_SYMBOLS: dict[type, str] = {
    ast.FloorDiv: "//",
    ast.Mod: "%",
    ast.MatMult: "@",
    ast.BitAnd: "&",
    ast.BitOr: "|",
    ast.BitXor: "^",
    ast.LShift: "<<",
    ast.RShift: ">>",
    ast.Not: "not",
    ast.Invert: "~",
    ast.Is: "is",
    ast.IsNot: "is not",
    ast.In: "in",
    ast.NotIn: "not in",
}

_DESCRIPTIONS: dict[type, str] = {
    ast.Import: "imports are not allowed",
    ast.ImportFrom: "imports are not allowed",
    ast.For: "loops are not allowed",
    ast.AsyncFor: "loops are not allowed",
    ast.While: "loops are not allowed",
    ast.If: "if-statements are not allowed; use a conditional expression (a if c else b)",
    ast.With: "with-statements are not allowed",
    ast.AsyncWith: "with-statements are not allowed",
    ast.Try: "try-statements are not allowed",
    ast.TryStar: "try-statements are not allowed",
    ast.Raise: "raise is not allowed",
    ast.Assert: "assert is not allowed",
    ast.Delete: "del is not allowed",
    ast.Global: "global declarations are not allowed",
    ast.Nonlocal: "nonlocal declarations are not allowed",
    ast.ClassDef: "class definitions are not allowed",
    ast.FunctionDef: "nested function definitions are not allowed",
    ast.AsyncFunctionDef: "async functions are not allowed",
    ast.Lambda: "lambda functions are not allowed",
    ast.ListComp: "comprehensions are not allowed",
    ast.SetComp: "comprehensions are not allowed",
    ast.DictComp: "comprehensions are not allowed",
    ast.GeneratorExp: "generator expressions are not allowed",
    ast.Yield: "yield is not allowed",
    ast.YieldFrom: "yield is not allowed",
    ast.Await: "await is not allowed",
    ast.NamedExpr: "the walrus operator := is not allowed",
    ast.JoinedStr: "f-strings are not allowed",
    ast.FormattedValue: "f-strings are not allowed",
    ast.Dict: "dictionaries are not allowed",
    ast.Set: "sets are not allowed",
    ast.List: "lists are only allowed in a return or an unpacking assignment",
    ast.Tuple: "tuples are only allowed in a return or an unpacking assignment",
    ast.Starred: "starred expressions (*x) are not allowed",
    ast.Slice: "slices are not allowed",
    ast.BoolOp: "'and' and 'or' are not allowed; use jnp.where",
    ast.Pass: "pass is not allowed",
    ast.Break: "break is not allowed",
    ast.Continue: "continue is not allowed",
    ast.AnnAssign: "annotated assignments are not allowed; write x = ...",
    ast.Match: "match statements are not allowed",
}


class SkeletonError(ValueError):
    """A skeleton was rejected: ``reason`` says why, ``line`` where (1 = the ``def`` line)."""

    def __init__(self, reason: str, line: int | None = None) -> None:
        self.reason = reason
        self.line = line
        super().__init__(str(self))

    def __str__(self) -> str:
        return f"line {self.line}: {self.reason}" if self.line else self.reason

    def __reduce__(self) -> tuple[Any, ...]:
        return (type(self), (self.reason, self.line))


@dataclass(frozen=True)
class Skeleton:
    """A checked and compiled skeleton.

    ``fn(*variables, p)`` takes the arrays of ``arguments`` in order and the parameter vector and
    returns a tuple of ``n_outputs`` arrays; calling the skeleton itself takes a mapping of named
    variables and returns the outputs stacked to ``[n_outputs, *sample_shape]``.
    ``length`` is the number of syntax-tree nodes of the body (without Load/Store markers), the
    code length used by the archive. ``n_constants`` counts numeric literals other than the
    indices of ``p``.
    """

    source: str
    name: str
    arguments: tuple[str, ...]
    n_params: int
    n_outputs: int
    n_constants: int
    length: int
    requests: tuple[dict, ...] = field(compare=False)
    fn: Callable[..., tuple[jax.Array, ...]] = field(repr=False, compare=False)

    def __call__(self, variables: Mapping[str, Any], p: Any) -> jax.Array:
        """Evaluate on named variables; returns ``[n_outputs, *sample_shape]`` (float)."""
        dtype = jnp.result_type(float)
        missing = [name for name in self.arguments if name not in variables]
        if missing:
            raise ValueError(
                f"skeleton {self.name!r} needs the variables {missing}, which are not given "
                f"(given: {sorted(variables)})"
            )
        p = jnp.asarray(p, dtype=dtype)
        if p.ndim != 1 or p.shape[0] < self.n_params:
            raise ValueError(
                f"skeleton {self.name!r} needs a parameter vector of length >= {self.n_params}, "
                f"got shape {p.shape}"
            )
        args = [jnp.asarray(variables[name], dtype=dtype) for name in self.arguments]
        outputs = [jnp.asarray(out, dtype=dtype) for out in self.fn(*args, p)]
        inputs = args if args else [jnp.asarray(v) for v in variables.values()]
        shape = np.broadcast_shapes(*(jnp.shape(x) for x in [*inputs, *outputs]))
        return jnp.stack([jnp.broadcast_to(out, shape) for out in outputs])


# ---------------------------------------------------------------------------------------------
# Extraction


_FENCE = re.compile(r"[ \t]*(`{3,}|~{3,})[ \t]*([\w+.-]*)")
_DEF = re.compile(r"([ \t]*)(?:async[ \t]+)?def[ \t]+([A-Za-z_]\w*)[ \t]*\(")
_MAX_JSON_TRIES = 20


def extract(text: str, function_name: str | None = None) -> tuple[str, tuple[dict, ...]]:
    """Find the skeleton's source and the variable requests in a model's answer.

    Code is taken from the markdown code fences that contain a ``def`` (or from the whole text if
    none does). The function is the last one named ``function_name`` if that is given, otherwise
    the last function that parses and whose last parameter is ``p`` (otherwise the last one, so
    that ``check`` can say what is wrong). Its lines are detabbed and dedented. Requests are the
    last ``json`` fence (or bare JSON object/list that ends the text) that parses: a list of
    dicts, or an object with a ``"variables"`` list; malformed JSON is ignored.
    Raises ``SkeletonError`` if no function is found.
    """
    if not isinstance(text, str):
        raise SkeletonError(f"the answer must be text, not {type(text).__name__}")
    if len(text) > MAX_ANSWER_CHARS:
        raise SkeletonError(
            f"the answer is {len(text)} characters long; at most {MAX_ANSWER_CHARS} are read"
        )
    lines = text.splitlines()
    code_blocks, json_texts, outside, last_fence = _split_fences(lines)

    regions = [block for block in code_blocks if any(_DEF.match(line) for line in block)]
    if not regions:
        regions = [outside]
    candidates = [c for region in regions for c in _functions(region)]
    if not candidates:
        raise SkeletonError("the answer contains no Python function (def name(..., p): ...)")
    if function_name is not None:
        named = [c for c in candidates if c[0] == function_name]
        if not named:
            found = ", ".join(sorted({c[0] for c in candidates}))
            raise SkeletonError(
                f"the answer has no function named {function_name!r} (found {found})"
            )
        source = named[-1][1]
    else:
        complete = [src for _, src in candidates if _ends_with_p(src)]
        source = complete[-1] if complete else candidates[-1][1]

    requests: tuple[dict, ...] = ()
    for blob in reversed(json_texts):
        requests = _requests(blob)
        if requests:
            break
    if not requests:
        requests = _trailing_json(lines, last_fence)
    return source, requests


def _split_fences(lines: list[str]) -> tuple[list[list[str]], list[str], list[str], int]:
    """Code fences, JSON texts, the lines outside fences (fences blanked), the last fence line."""
    code_blocks: list[list[str]] = []
    json_texts: list[str] = []
    outside: list[str] = []
    block: list[str] | None = None
    language = ""
    last_fence = -1
    for index, line in enumerate(lines):
        match = _FENCE.match(line)
        if match:
            last_fence = index
            outside.append("")
            opening = block is None or bool(match.group(2))  # ```lang also ends an open fence
            if block is not None:
                _file_block(block, language, code_blocks, json_texts)
                block = None
            if opening:
                block, language = [], match.group(2).lower()
            continue
        if block is None:
            outside.append(line)
        else:
            block.append(line)
            outside.append("")
    if block is not None:  # an unclosed fence: the answer was cut off
        _file_block(block, language, code_blocks, json_texts)
    return code_blocks, json_texts, outside, last_fence


def _file_block(block: list[str], language: str, code: list[list[str]], data: list[str]) -> None:
    content = "\n".join(block).strip()
    if language == "json" or (language in ("", "javascript", "js") and content[:1] in "{["):
        data.append(content)
    else:
        code.append(block)


def _functions(lines: list[str]) -> list[tuple[str, str]]:
    """The top-level ``def`` blocks of a region: (name, dedented source)."""
    found = []
    index = floor = 0
    while index < len(lines):
        match = _DEF.match(lines[index])
        if match is None:
            index += 1
            continue
        indent = _width(match.group(1))
        depth = _bracket_delta(lines[index])
        end = index + 1
        while end < len(lines):
            line = lines[end]
            if line.strip():
                leading = line[: len(line) - len(line.lstrip())]
                if depth <= 0 and _width(leading) <= indent:
                    break
                depth += _bracket_delta(line)
            end += 1
        start = index  # decorators belong to the function, so that check() rejects them
        while start > floor and lines[start - 1].lstrip().startswith("@"):
            start -= 1
        block = [_detab(line) for line in lines[start:end]]
        found.append((match.group(2), textwrap.dedent("\n".join(block)).strip("\n") + "\n"))
        index = floor = end
    return found


def _width(whitespace: str) -> int:
    return len(whitespace.replace("\u00a0", " ").expandtabs(4))


def _detab(line: str) -> str:
    stripped = line.lstrip(" \t\u00a0")
    leading = line[: len(line) - len(stripped)]
    return " " * _width(leading) + stripped.rstrip()


def _bracket_delta(line: str) -> int:
    code = line.split("#", 1)[0]
    return sum(code.count(c) for c in "([{") - sum(code.count(c) for c in ")]}")


def _ends_with_p(source: str) -> bool:
    if len(source) > MAX_SOURCE_CHARS:
        return False
    try:
        tree = _parse(source)
    except Exception:  # SyntaxError, RecursionError, MemoryError, ValueError: not complete
        return False
    if len(tree.body) != 1 or not isinstance(tree.body[0], ast.FunctionDef):
        return False
    args = tree.body[0].args.args
    return bool(args) and args[-1].arg == "p"


def _trailing_json(lines: list[str], last_fence: int) -> tuple[dict, ...]:
    """A bare JSON object or list that ends the answer (after the last fence and ``def``)."""
    start = last_fence + 1
    for index in range(len(lines) - 1, start - 1, -1):
        if _DEF.match(lines[index]):
            start = index + 1
            break
    starts = [i for i in range(start, len(lines)) if lines[i].lstrip()[:1] in ("{", "[")]
    for index in starts[:_MAX_JSON_TRIES]:
        requests = _requests("\n".join(lines[index:]).strip())
        if requests:
            return requests
    return ()


def _requests(blob: str) -> tuple[dict, ...]:
    """Parse variable requests; anything malformed gives ``()``."""
    if not blob or len(blob) > 50_000:
        return ()
    try:
        obj = json.loads(blob)
    except (ValueError, RecursionError):
        return ()
    items: Any = []
    if isinstance(obj, list):
        items = obj
    elif isinstance(obj, dict):
        for key in ("variables", "requests"):
            if isinstance(obj.get(key), list):
                items = obj[key]
                break
        else:
            items = [obj] if "name" in obj else []
    out = []
    for item in items:
        if isinstance(item, dict):
            out.append(dict(item))
        elif isinstance(item, str):
            out.append({"name": item})
    return tuple(out)


# ---------------------------------------------------------------------------------------------
# Checking


def check(
    source: str, *, variables: Sequence[str], n_outputs: int | None = None
) -> ast.FunctionDef:
    """Parse ``source`` and check it against the whitelist; returns the normalised function tree.

    The tree has its docstring and annotations removed. Raises ``SkeletonError`` naming the line
    and the reason of the first violation.
    """
    if not isinstance(source, str):
        raise SkeletonError(f"the skeleton must be text, not {type(source).__name__}")
    if len(source) > MAX_SOURCE_CHARS:
        raise SkeletonError(
            f"the function is {len(source)} characters long; at most {MAX_SOURCE_CHARS} are allowed"
        )
    library = _library(variables)
    try:
        tree = _parse(source)
    except SyntaxError as error:  # also IndentationError, TabError
        raise SkeletonError(f"the code is not valid Python: {error.msg}", error.lineno) from None
    except (RecursionError, MemoryError):
        raise SkeletonError("the code is nested too deeply to be parsed") from None
    except ValueError as error:  # null bytes and the like
        raise SkeletonError(f"the code cannot be parsed: {error}") from None
    _measure(tree)
    return _Checker(library, n_outputs).module(tree)


def _parse(source: str) -> ast.Module:
    """``ast.parse`` without its SyntaxWarnings (such as "invalid decimal literal")."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return ast.parse(source, mode="exec")


def _library(variables: Sequence[str]) -> frozenset[str]:
    if isinstance(variables, str):
        raise SkeletonError("variables must be a sequence of names, not a single string")
    names = []
    for name in variables:
        invalid = not isinstance(name, str) or not name.isidentifier() or keyword.iskeyword(name)
        if invalid or name.startswith("_"):
            raise SkeletonError(f"the variable library has an invalid name {name!r}")
        if name in _RESERVED:
            raise SkeletonError(f"the variable library uses the reserved name {name!r}")
        names.append(name)
    return frozenset(names)


def _measure(tree: ast.AST) -> None:
    """Reject trees that are too large or too deep, without recursion."""
    stack: list[tuple[ast.AST, int, int | None]] = [(tree, 0, None)]
    count = 0
    while stack:
        node, depth, line = stack.pop()
        if isinstance(node, ast.expr_context):
            continue
        line = getattr(node, "lineno", line)
        count += 1
        if count > MAX_NODES:
            raise SkeletonError(f"the function is too long: more than {MAX_NODES} syntax nodes")
        if depth > MAX_DEPTH:
            raise SkeletonError(
                f"the code is nested too deeply (more than {MAX_DEPTH} levels)", line
            )
        stack.extend((child, depth + 1, line) for child in ast.iter_child_nodes(node))


def _count_nodes(nodes: Sequence[ast.AST]) -> int:
    return sum(
        1 for root in nodes for node in ast.walk(root) if not isinstance(node, ast.expr_context)
    )


def _describe(node: ast.AST) -> str:
    return _DESCRIPTIONS.get(type(node), f"the construct {type(node).__name__!r} is not allowed")


def _short(node: ast.AST) -> str:
    text = ast.unparse(node)
    return text if len(text) <= 40 else text[:37] + "..."


class _Checker:
    """One pass over a parsed function; raises SkeletonError at the first violation."""

    def __init__(self, library: frozenset[str], n_outputs: int | None) -> None:
        self.library = library
        self.n_outputs = n_outputs
        self.defined: set[str] = set()
        self.line: int | None = None

    def fail(self, reason: str, node: ast.AST | None = None) -> SkeletonError:
        line = getattr(node, "lineno", None) or self.line
        return SkeletonError(reason, line)

    def module(self, tree: ast.Module) -> ast.FunctionDef:
        functions = [s for s in tree.body if isinstance(s, ast.FunctionDef)]
        for statement in tree.body:
            if not isinstance(statement, ast.FunctionDef):
                if isinstance(statement, ast.AsyncFunctionDef):
                    raise self.fail("async functions are not allowed", statement)
                if isinstance(statement, ast.Expr):
                    raise self.fail("code outside the function is not allowed", statement)
                raise self.fail(_describe(statement) + " (outside the function)", statement)
        if not functions:
            raise SkeletonError("the code contains no function definition")
        if len(functions) > 1:
            raise self.fail("only one function may be defined", functions[1])
        return self.function(functions[0])

    def function(self, fdef: ast.FunctionDef) -> ast.FunctionDef:
        self.line = fdef.lineno
        self.name(fdef.name, fdef, "function name")
        if fdef.decorator_list:
            raise self.fail("decorators are not allowed", fdef.decorator_list[0])
        args = fdef.args
        if args.posonlyargs or args.kwonlyargs or args.vararg or args.kwarg:
            raise self.fail("only plain positional parameters are allowed (no /, *, *args, **kw)")
        if args.defaults or args.kw_defaults:
            raise self.fail("parameters may not have default values")
        names = [a.arg for a in args.args]
        if not names or names[-1] != "p":
            raise self.fail("the last parameter must be the parameter vector p")
        if len(set(names)) != len(names):
            raise self.fail("a parameter name is repeated")
        unknown = [n for n in names[:-1] if n not in self.library]
        if unknown:
            allowed = ", ".join(sorted(self.library)) or "none"
            raise self.fail(
                f"the function takes {', '.join(map(repr, unknown))}, which "
                f"{'is' if len(unknown) == 1 else 'are'} not in the variable library "
                f"(allowed: {allowed})"
            )
        for arg in args.args:
            if arg.annotation is not None:
                self.annotation(arg.annotation)
                arg.annotation = None
        if fdef.returns is not None:
            self.annotation(fdef.returns)
            fdef.returns = None
        fdef.type_comment = None
        for arg in args.args:
            arg.type_comment = None

        body = list(fdef.body)
        first = body[0]
        is_docstring = isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant)
        if is_docstring and isinstance(first.value.value, str):  # type: ignore[attr-defined]
            body = body[1:]
        if not body:
            raise self.fail("the function has no body")
        self.defined = set(names[:-1])
        for statement in body[:-1]:
            if isinstance(statement, ast.Return):
                raise self.fail("only one return is allowed, as the last statement", statement)
            self.statement(statement)
        last = body[-1]
        if not isinstance(last, ast.Return):
            self.statement(last)
            raise self.fail("the function must end with a return statement", last)
        self.returns(last)
        fdef.body = body
        return fdef

    def annotation(self, node: ast.expr) -> None:
        for sub in ast.walk(node):
            allowed = (ast.Name, ast.Attribute, ast.Subscript, ast.Tuple, ast.expr_context)
            if isinstance(sub, ast.Constant) and sub.value is None:
                continue
            if isinstance(sub, ast.BinOp) and isinstance(sub.op, ast.BitOr):
                continue
            if not isinstance(sub, (*allowed, ast.BitOr)):
                raise self.fail("annotations may only be plain type names", node)
            name = sub.id if isinstance(sub, ast.Name) else getattr(sub, "attr", "")
            if name.startswith("_"):
                raise self.fail(f"uses the name {name!r}; names starting with _ are not allowed")

    def name(self, name: str, node: ast.AST, what: str) -> None:
        if name.startswith("_"):
            kind = "dunder names" if name.startswith("__") else "names starting with _"
            raise self.fail(f"uses the {what} {name!r}; {kind} are not allowed", node)

    def target(self, node: ast.expr) -> str:
        self.line = getattr(node, "lineno", self.line)
        if not isinstance(node, ast.Name):
            if isinstance(node, ast.Attribute | ast.Subscript):
                raise self.fail(
                    f"assigns to {_short(node)}; only simple local names may be assigned"
                )
            raise self.fail(_describe(node), node)
        self.name(node.id, node, "name")
        if node.id in _RESERVED:
            raise self.fail(f"assigns to {node.id!r}, which is reserved (p or a math name)", node)
        return node.id

    def statement(self, node: ast.stmt) -> None:
        self.line = node.lineno
        if isinstance(node, ast.Assign):
            targets = node.targets
            if any(isinstance(t, ast.Tuple | ast.List) for t in targets):
                if len(targets) != 1:
                    raise self.fail("chained assignment with unpacking is not allowed", node)
                elements = targets[0].elts  # type: ignore[attr-defined]
                value = node.value
                if not isinstance(value, ast.Tuple | ast.List) or len(value.elts) != len(elements):
                    raise self.fail(
                        "unpacking is only allowed from a tuple of the same length (a, b = x, y)",
                        node,
                    )
                for element in value.elts:
                    self.expr(element)
                new = [self.target(t) for t in elements]
            else:
                self.expr(node.value)
                new = [self.target(t) for t in targets]
            self.defined.update(new)
        elif isinstance(node, ast.AugAssign):
            if not isinstance(node.target, ast.Name):
                raise self.fail(
                    f"assigns to {_short(node.target)}; only local names may be assigned"
                )
            name = self.target(node.target)
            if name not in self.defined:
                raise self.fail(f"updates {name!r} before it is assigned", node)
            self.binop(node.op, node.target, node.value, node)
        elif isinstance(node, ast.Expr):
            self.expr(node.value)
            raise self.fail(
                "a bare expression has no effect; only assignments and the final return "
                "are allowed",
                node,
            )
        else:
            raise self.fail(_describe(node), node)

    def returns(self, node: ast.Return) -> None:
        self.line = node.lineno
        value = node.value
        if value is None:
            raise self.fail("the return statement returns nothing", node)
        elements = value.elts if isinstance(value, ast.Tuple | ast.List) else [value]
        if not elements:
            raise self.fail("the return statement returns an empty tuple", node)
        for element in elements:
            self.expr(element)
        if self.n_outputs is not None and len(elements) != self.n_outputs:
            raise self.fail(
                f"the function returns {len(elements)} value{'s' * (len(elements) != 1)} "
                f"but the task needs {self.n_outputs}",
                node,
            )

    def binop(self, op: ast.operator, left: ast.expr, right: ast.expr, node: ast.AST) -> None:
        if type(op) not in _OPERATORS:
            symbol = _SYMBOLS.get(type(op), type(op).__name__)
            raise self.fail(f"uses the operator {symbol!r}, which is not allowed", node)
        self.expr(left)
        if isinstance(op, ast.Pow):
            self.exponent(right)
        else:
            self.expr(right)

    def exponent(self, node: ast.expr) -> None:
        inner = node.operand if isinstance(node, ast.UnaryOp) else node
        if (
            isinstance(node, ast.UnaryOp)
            and isinstance(node.op, ast.USub | ast.UAdd)
            and _is_param(inner)
        ):
            self.expr(inner)
            return
        if _is_param(node):
            self.expr(node)
            return
        if any(isinstance(n, ast.BinOp) and isinstance(n.op, ast.Pow) for n in ast.walk(node)):
            raise self.fail("uses a chain of powers (x ** a ** b), which is not allowed", node)
        value = _fold(node)
        if value is None:
            raise self.fail(
                f"raises to the power {_short(node)}; exponents must be numbers between "
                f"-{MAX_EXPONENT} and {MAX_EXPONENT} or a parameter p[i]",
                node,
            )
        self.expr(node)  # validates and counts the literals
        if not math.isfinite(value) or abs(value) > MAX_EXPONENT:
            raise self.fail(
                f"raises to the power {_short(node)}; constant exponents must lie between "
                f"-{MAX_EXPONENT} and {MAX_EXPONENT}",
                node,
            )

    def expr(self, node: ast.expr) -> None:
        self.line = getattr(node, "lineno", self.line)
        if isinstance(node, ast.Constant):
            self.constant(node)
        elif isinstance(node, ast.Name):
            self.load(node)
        elif isinstance(node, ast.Attribute):
            name = _math_name(node)
            if name is not None and name in _CONSTANTS:
                return
            if name is not None and (name in FUNCTIONS or name in ALIASES):
                raise self.fail(f"uses the function {_short(node)} without calling it", node)
            if node.attr.startswith("_"):
                raise self.fail(
                    f"accesses {node.attr!r}; dunder and private names are not allowed", node
                )
            raise self.fail(
                f"accesses the attribute {_short(node)}; only math names such as jnp.sin or "
                "jnp.pi are allowed",
                node,
            )
        elif isinstance(node, ast.Subscript):
            if not _is_param(node):
                raise self.fail(f"indexes {_short(node.value)}; only p[i] may be indexed", node)
            index = node.slice
            valid = (
                isinstance(index, ast.Constant)
                and isinstance(index.value, int)
                and not isinstance(index.value, bool)
            )
            if not valid or not 0 <= index.value < MAX_PARAMS:  # type: ignore[union-attr]
                raise self.fail(
                    f"uses p[{_short(index)}]; parameters must be p[0] ... p[{MAX_PARAMS - 1}] "
                    "with an integer literal index",
                    node,
                )
        elif isinstance(node, ast.BinOp):
            self.binop(node.op, node.left, node.right, node)
        elif isinstance(node, ast.UnaryOp):
            if not isinstance(node.op, ast.USub | ast.UAdd):
                symbol = _SYMBOLS.get(type(node.op), type(node.op).__name__)
                raise self.fail(f"uses the operator {symbol!r}, which is not allowed", node)
            self.expr(node.operand)
        elif isinstance(node, ast.Compare):
            for op in node.ops:
                if not isinstance(op, _COMPARISONS):
                    symbol = _SYMBOLS.get(type(op), type(op).__name__)
                    raise self.fail(f"uses the comparison {symbol!r}, which is not allowed", node)
            self.expr(node.left)
            for comparator in node.comparators:
                self.expr(comparator)
        elif isinstance(node, ast.IfExp):
            self.expr(node.test)
            self.expr(node.body)
            self.expr(node.orelse)
        elif isinstance(node, ast.Call):
            self.call(node)
        else:
            raise self.fail(_describe(node), node)

    def constant(self, node: ast.Constant) -> None:
        value = node.value
        if isinstance(value, bool) or value is None or value is Ellipsis:
            raise self.fail(f"uses {value!r}; only numbers are allowed as constants", node)
        if isinstance(value, str | bytes):
            raise self.fail("strings are not allowed", node)
        if isinstance(value, complex):
            raise self.fail("complex numbers are not allowed", node)
        if not isinstance(value, int | float):
            raise self.fail(f"the constant {value!r} is not allowed", node)
        if isinstance(value, int) and value.bit_length() > 64:
            raise self.fail(
                f"the literal {_short(node)} is too large (limit {MAX_LITERAL:g})", node
            )
        if not math.isfinite(value) or abs(value) > MAX_LITERAL:
            raise self.fail(
                f"the literal {_short(node)} is too large (limit {MAX_LITERAL:g})", node
            )

    def load(self, node: ast.Name) -> None:
        name = node.id
        self.name(name, node, "name")
        if name == "p":
            raise self.fail("uses p on its own; parameters must be written p[0], p[1], ...", node)
        if name in self.defined or name in _BARE_CONSTANTS:
            return
        if name in FUNCTIONS or name in ALIASES:
            raise self.fail(f"uses the function {name!r} without calling it", node)
        raise self.fail(
            f"uses the name {name!r}, which is not a parameter, an earlier assignment or an "
            "allowed math constant",
            node,
        )

    def call(self, node: ast.Call) -> None:
        func = node.func
        name: str | None = None
        if isinstance(func, ast.Name) and func.id not in self.defined:
            name = func.id
        else:
            name = _math_name(func)
        canonical = ALIASES.get(name, name) if name is not None else None
        if canonical not in FUNCTIONS:
            if isinstance(func, ast.Lambda):
                raise self.fail("lambda functions are not allowed", node)
            for sub in ast.walk(func):
                hidden = getattr(sub, "id", None) or getattr(sub, "attr", None) or ""
                if hidden.startswith("_"):
                    self.name(hidden, node, "name")
            raise self.fail(f"calls '{_short(func)}', which is not an allowed math function", node)
        if node.keywords:
            raise self.fail(
                f"passes keyword arguments to {_short(func)}; use positional ones", node
            )
        if any(isinstance(a, ast.Starred) for a in node.args):
            raise self.fail(f"passes *arguments to {_short(func)}; this is not allowed", node)
        arity = FUNCTIONS[canonical][1]
        if len(node.args) != arity:
            raise self.fail(
                f"calls {_short(func)} with {len(node.args)} argument"
                f"{'s' * (len(node.args) != 1)}; it takes {arity}",
                node,
            )
        for arg in node.args:
            self.expr(arg)


# ---------------------------------------------------------------------------------------------
# Compiling


class _Rewriter(ast.NodeTransformer):
    """Turn a checked tree into the tree that is compiled (see the module docstring)."""

    def __init__(self) -> None:
        self.constants: list[float] = []
        self.temporaries = 0

    def temporary(self) -> str:
        """A fresh local name (a skeleton's own names never start with an underscore)."""
        self.temporaries += 1
        return f"_t{self.temporaries - 1}"

    def constant(self, value: float) -> ast.Name:
        self.constants.append(float(value))
        return ast.Name(id=f"_k{len(self.constants) - 1}", ctx=ast.Load())

    def visit_Constant(self, node: ast.Constant) -> ast.AST:
        return self.constant(node.value)

    def visit_Name(self, node: ast.Name) -> ast.AST:
        if isinstance(node.ctx, ast.Load) and node.id in _BARE_CONSTANTS:
            return ast.Name(id=f"_m_{node.id}", ctx=ast.Load())
        return node

    def visit_Attribute(self, node: ast.Attribute) -> ast.AST:  # only math constants remain
        return ast.Name(id=f"_m_{_math_name(node)}", ctx=ast.Load())

    def visit_Subscript(self, node: ast.Subscript) -> ast.AST:  # only p[i]
        return node

    def visit_Call(self, node: ast.Call) -> ast.AST:
        func = node.func
        name = func.id if isinstance(func, ast.Name) else _math_name(func)
        canonical = ALIASES.get(name, name)  # type: ignore[arg-type]
        args = [self.visit(a) for a in node.args]
        return ast.Call(func=ast.Name(id=f"_m_{canonical}", ctx=ast.Load()), args=args, keywords=[])

    def visit_BinOp(self, node: ast.BinOp) -> ast.AST:
        left = self.visit(node.left)
        if isinstance(node.op, ast.Pow):
            value = _fold(node.right)
            right = self.visit(node.right) if value is None else ast.Constant(value=value)
        else:
            right = self.visit(node.right)
        return ast.BinOp(left=left, op=node.op, right=right)

    def visit_IfExp(self, node: ast.IfExp) -> ast.AST:
        args = [self.visit(node.test), self.visit(node.body), self.visit(node.orelse)]
        return ast.Call(func=ast.Name(id="_m_where", ctx=ast.Load()), args=args, keywords=[])

    def visit_Compare(self, node: ast.Compare) -> ast.AST:
        # Python evaluates each operand of a chain once; so does the rewrite. A middle operand
        # (the right side of one pair and the left of the next) that is more than a name or p[i]
        # is bound to a temporary where it is first used (``a < (_t0 := b)``, then ``_t0 < c``):
        # copying it instead would double the tree at every level of nested chains.
        operands = [self.visit(node.left), *(self.visit(c) for c in node.comparators)]
        pairs: list[ast.expr] = []
        left = operands[0]
        for i, op in enumerate(node.ops):
            right = operands[i + 1]
            if i == len(node.ops) - 1:
                shared = right
            elif _is_leaf(right):
                shared = copy.deepcopy(right)  # a name or p[i]: at most four nodes
            else:
                name = self.temporary()
                right = ast.NamedExpr(target=ast.Name(id=name, ctx=ast.Store()), value=right)
                shared = ast.Name(id=name, ctx=ast.Load())
            pairs.append(ast.Compare(left=left, ops=[op], comparators=[right]))
            left = shared
        result = pairs[0]
        for pair in pairs[1:]:
            func = ast.Name(id="_m_logical_and", ctx=ast.Load())
            result = ast.Call(func=func, args=[result, pair], keywords=[])
        # comparisons are numbers (0.0 or 1.0), as in Python: -(a < b) and (a < b) + (c < d) work
        return ast.Call(func=ast.Name(id="_m_float", ctx=ast.Load()), args=[result], keywords=[])

    def visit_Return(self, node: ast.Return) -> ast.AST:
        value = node.value
        elements = value.elts if isinstance(value, ast.Tuple | ast.List) else [value]
        return ast.Return(value=ast.Tuple(elts=[self.visit(e) for e in elements], ctx=ast.Load()))


def _is_leaf(node: ast.expr) -> bool:
    """A rewritten operand that is cheap to repeat: a name (a variable, a local, a constant) or
    ``p[i]``."""
    return isinstance(node, ast.Name) or _is_param(node)


def _as_float(x: jax.Array) -> jax.Array:
    return jnp.asarray(x, dtype=jnp.result_type(float))


def _build(
    fdef: ast.FunctionDef, n_outputs: int, requests: tuple[dict, ...], n_params: int
) -> Skeleton:
    """Compile a checked function tree into a Skeleton."""
    source = ast.unparse(fdef)
    body = fdef.body
    n_constants = sum(
        1
        for statement in body
        for node in ast.walk(statement)
        if isinstance(node, ast.Constant) and not isinstance(node.value, str)
    ) - sum(1 for statement in body for node in ast.walk(statement) if _is_param(node))

    compiled, constants = _rewrite(fdef)
    module = ast.fix_missing_locations(ast.Module(body=[compiled], type_ignores=[]))
    code = compile(module, filename=f"<skeleton {fdef.name}>", mode="exec")
    dtype = jnp.result_type(float)
    namespace: dict[str, Any] = {"__builtins__": {}}
    namespace.update({f"_m_{name}": function for name, (function, _) in FUNCTIONS.items()})
    namespace["_m_logical_and"] = jnp.logical_and
    namespace["_m_float"] = _as_float
    # device_put, not jnp.asarray (which compiles a small program per shape in this JAX)
    namespace.update(
        {f"_m_{name}": jax.device_put(np.asarray(v, dtype)) for name, v in _CONSTANTS.items()}
    )
    namespace.update(
        {f"_k{i}": jax.device_put(np.asarray(v, dtype)) for i, v in enumerate(constants)}
    )
    exec(code, namespace)  # defines the function only: no defaults, decorators or annotations
    _lower(source)
    interp.register(namespace[fdef.name], source)  # the fitter runs it as a program instead
    return Skeleton(
        source=source,
        name=fdef.name,
        arguments=tuple(a.arg for a in fdef.args.args[:-1]),
        n_params=n_params,
        n_outputs=n_outputs,
        n_constants=n_constants,
        length=_count_nodes(body),
        requests=requests,
        fn=namespace[fdef.name],
    )


def _rewrite(fdef: ast.FunctionDef) -> tuple[ast.FunctionDef, list[float]]:
    """The tree that is compiled and its constants; checks ``MAX_COMPILED_NODES``."""
    rewriter = _Rewriter()
    compiled = rewriter.visit(copy.deepcopy(fdef))
    _within_budget(_count_nodes([compiled]), MAX_COMPILED_NODES, "syntax nodes once rewritten")
    return compiled, rewriter.constants


def sizes(source: str, *, variables: Sequence[str], n_outputs: int | None = None) -> dict[str, int]:
    """The size of a skeleton after each transformation (for tests of the budgets).

    ``nodes``: the checked function's syntax nodes (without Load/Store markers); ``compiled``:
    nodes of the rewritten tree that is compiled; ``instructions``: the instructions of the
    interpreter's programs (main, features, one per output) together.
    Raises ``SkeletonError`` where ``check`` or a budget rejects the source.
    """
    fdef = check(source, variables=variables, n_outputs=n_outputs)
    compiled, _ = _rewrite(fdef)
    program = interp.lowered(ast.unparse(fdef))
    parts = [] if program is None else [program, *program.parts]
    if program is not None and program.features is not None:
        parts.append(program.features)
    return {
        "nodes": _count_nodes([fdef]),
        "compiled": _count_nodes([compiled]),
        "instructions": sum(part.length for part in parts),
    }


def _within_budget(size: int, limit: int, what: str) -> None:
    if size > limit:
        raise SkeletonError(f"the skeleton is too large: {size} {what} (limit {limit})")


def _lower(source: str) -> None:
    """Lower the checked source to the interpreter's program (cached for the fitter) and check
    its size; a skeleton the interpreter cannot run otherwise is fitted through its function."""
    program = interp.lowered(source)
    if program is None:
        try:
            interp.lower(source)
        except interp.ProgramTooLarge as error:
            raise SkeletonError(f"the skeleton is too large once lowered: {error}") from None
        except interp.LoweringError:
            return
        return
    sizes = [program, *program.parts, *([program.features] if program.features else [])]
    for part in sizes:
        _within_budget(part.length, MAX_PROGRAM_INSTRUCTIONS, "instructions once lowered")


def compile_skeleton(
    text: str,
    *,
    variables: Sequence[str],
    n_outputs: int,
    function_name: str | None = None,
) -> Skeleton:
    """Extract, check and compile a skeleton from a model's answer.

    Raises ``SkeletonError`` and nothing else: an unexpected exception (a bug here) is reported
    as a ``SkeletonError`` whose reason starts with ``"internal error"``.
    """
    try:
        source, requests = extract(text, function_name)
        checker_tree = check(source, variables=variables, n_outputs=n_outputs)
        n_params = _n_params(checker_tree)
        n_out = _n_returned(checker_tree)
        return _build(checker_tree, n_out, requests, n_params)
    except SkeletonError:
        raise
    except Exception as error:
        raise SkeletonError(
            f"internal error while compiling the skeleton ({type(error).__name__}: {error})"
        ) from error


def try_compile(
    text: str,
    *,
    variables: Sequence[str],
    n_outputs: int,
    function_name: str | None = None,
) -> Skeleton | SkeletonError:
    """Like ``compile_skeleton``, but returns the ``SkeletonError`` instead of raising it."""
    try:
        return compile_skeleton(
            text, variables=variables, n_outputs=n_outputs, function_name=function_name
        )
    except SkeletonError as error:
        return error


def _n_params(fdef: ast.FunctionDef) -> int:
    indices = [
        node.slice.value  # type: ignore[attr-defined]
        for statement in fdef.body
        for node in ast.walk(statement)
        if _is_param(node)
    ]
    return 1 + max(indices) if indices else 0


def _n_returned(fdef: ast.FunctionDef) -> int:
    value = fdef.body[-1].value  # type: ignore[attr-defined]
    return len(value.elts) if isinstance(value, ast.Tuple | ast.List) else 1


# ---------------------------------------------------------------------------------------------
# Probing


def probe(
    skeleton: Skeleton, variables: Mapping[str, Any], key: jax.Array, *, tries: int = 3
) -> jax.Array:
    """Evaluate once on data with random parameters; returns ``[n_outputs, *sample_shape]``.

    Parameters are drawn from a standard normal, up to ``tries`` times. Raises ``SkeletonError``
    if evaluation fails, the outputs have the wrong shape, or some output is non-finite at every
    sample for every draw.
    """
    shapes = [jnp.shape(v) for v in variables.values()]
    try:
        sample_shape = np.broadcast_shapes(*shapes) if shapes else ()
    except ValueError as error:
        raise SkeletonError(f"the variables have incompatible shapes: {error}") from None
    expected = (skeleton.n_outputs, *sample_shape)
    bad = 0
    for subkey in jax.random.split(key, tries):
        p = jax.random.normal(subkey, (skeleton.n_params,), dtype=jnp.result_type(float))
        try:
            out = skeleton(variables, p)
        except Exception as error:
            message = str(error).splitlines()[0][:200] if str(error) else ""
            raise SkeletonError(
                f"evaluating the skeleton failed ({type(error).__name__}: {message})"
            ) from None
        if out.shape != expected:
            raise SkeletonError(f"the skeleton's outputs have shape {out.shape}, not {expected}")
        finite = np.asarray(jnp.isfinite(out).reshape(skeleton.n_outputs, -1).any(axis=1))
        if finite.all():
            return out
        bad = int(np.argmin(finite))
    raise SkeletonError(
        f"output {bad + 1} is not finite (nan or inf) at any sample for {tries} random "
        "parameter vectors"
    )
