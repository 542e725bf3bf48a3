"""Compiling: a checked tree -> a pure JAX function and the interpreter's program; probing."""

from __future__ import annotations

import ast
from collections.abc import Mapping, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxdmd import interp
from jaxdmd.lines import copy_tree
from jaxdmd.skeleton.checking import check
from jaxdmd.skeleton.core import (
    _BARE_CONSTANTS,
    _CONSTANTS,
    ALIASES,
    FUNCTIONS,
    MAX_NODES,
    Skeleton,
    SkeletonError,
    _count_nodes,
    _fold,
    _is_param,
    _math_name,
)
from jaxdmd.skeleton.extraction import extract

__all__ = [
    "MAX_COMPILED_NODES",
    "MAX_PROGRAM_INSTRUCTIONS",
    "compile_skeleton",
    "probe",
    "sizes",
    "try_compile",
]

# Budgets after each transformation, so that compiling and evaluating a candidate cost at most a
# constant times its (checked, bounded) size. The rewrite adds a fixed number of nodes per node
# (a comparison pair: the call to logical_and, a temporary for a shared operand, the float
# conversion), and lowering emits a bounded number of instructions per node (an integer power
# at most 2 log2(MAX_EXPONENT) + 1); the measured worst cases lie far below these limits.
MAX_COMPILED_NODES = 8 * MAX_NODES  # nodes of the rewritten tree that is compiled
MAX_PROGRAM_INSTRUCTIONS = interp.MAX_INSTRUCTIONS  # instructions of the lowered program


class _Rewriter(ast.NodeTransformer):
    """Turn a checked tree into the tree that is compiled (see :mod:`jaxdmd.skeleton`)."""

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
                shared = copy_tree(right)  # a name or p[i]: at most four nodes
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
    compiled = rewriter.visit(copy_tree(fdef))
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
