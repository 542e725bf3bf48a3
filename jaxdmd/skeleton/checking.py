"""Checking: a skeleton's source against the whitelist (see :mod:`jaxdmd.skeleton`)."""

from __future__ import annotations

import ast
import keyword
import math
from collections.abc import Sequence

from jaxdmd.skeleton.core import (
    _BARE_CONSTANTS,
    _CONSTANTS,
    _RESERVED,
    ALIASES,
    FUNCTIONS,
    MAX_DEPTH,
    MAX_EXPONENT,
    MAX_LITERAL,
    MAX_NODES,
    MAX_PARAMS,
    MAX_SOURCE_CHARS,
    SkeletonError,
    _fold,
    _is_param,
    _math_name,
    _parse,
)

__all__ = ["check"]

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
