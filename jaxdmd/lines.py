"""Equation lines: a skeleton seen as one expression per output, and skeletons assembled from lines.

The state equations of a dynamic model are separable: each output of a skeleton is its own
equation with its own parameters. This module turns a *checked* skeleton source into one
self-contained expression per output (local assignments inlined, parameters renumbered from
``p[0]``) and assembles a new skeleton from such lines. The search uses it to recombine the best
line of each equation across candidates, the offline proposer to edit equations term by term.

Only sources that passed :func:`jaxdmd.skeleton.check` are handed here; nothing here executes code.
"""

from __future__ import annotations

import ast
import functools
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TypeVar

_Tree = TypeVar("_Tree", bound="ast.AST | list")


@dataclass(frozen=True)
class Line:
    """One output equation: an expression over named variables and ``p[0] .. p[n_params-1]``."""

    expr: ast.expr
    n_params: int

    @functools.cached_property
    def text(self) -> str:  # once per line: a line's expression is never changed in place
        return ast.unparse(self.expr)

    def variables(self) -> frozenset[str]:
        return frozenset(
            n.id for n in ast.walk(self.expr) if isinstance(n, ast.Name) and n.id != "p"
        )


def param_index(node: ast.AST) -> int | None:
    """``i`` if ``node`` is the parameter ``p[i]``, else None."""
    if (
        isinstance(node, ast.Subscript)
        and isinstance(node.value, ast.Name)
        and node.value.id == "p"
        and isinstance(node.slice, ast.Constant)
        and isinstance(node.slice.value, int)
    ):
        return node.slice.value
    return None


def param_indices(node: ast.AST) -> list[int]:
    """The index of every parameter ``p[i]`` in ``node``, in :func:`ast.walk` order."""
    return [i for i in map(param_index, ast.walk(node)) if i is not None]


def copy_tree(node: _Tree) -> _Tree:
    """A deep copy of a syntax tree (or a list of them): what :func:`copy.deepcopy` gives,
    about four times faster on an equation's tree (a tree holds only nodes, lists and
    immutable values, so nothing else needs copying or a memo of what was copied)."""
    if isinstance(node, ast.AST):
        new = node.__class__.__new__(node.__class__)
        fields = new.__dict__
        for name, value in node.__dict__.items():
            fields[name] = copy_tree(value) if isinstance(value, (ast.AST, list)) else value
        return new  # type: ignore[return-value]
    return [copy_tree(x) if isinstance(x, (ast.AST, list)) else x for x in node]  # type: ignore[return-value,union-attr]


class _Inline(ast.NodeTransformer):
    def __init__(self, env: dict[str, ast.expr]):
        self.env = env

    def visit_Name(self, node: ast.Name) -> ast.expr:
        if node.id in self.env:
            return copy_tree(self.env[node.id])
        return node


class _Renumber(ast.NodeTransformer):
    """Renumber ``p[i]`` to consecutive indices starting at ``offset``, in order of appearance."""

    def __init__(self, offset: int = 0):
        self.mapping: dict[int, int] = {}
        self.offset = offset

    def visit_Subscript(self, node: ast.Subscript) -> ast.expr:
        index = param_index(node)
        if index is None:
            return self.generic_visit(node)
        if index not in self.mapping:
            self.mapping[index] = self.offset + len(self.mapping)
        return _p(self.mapping[index])


def _p(index: int) -> ast.Subscript:
    return ast.Subscript(value=ast.Name("p", ast.Load()), slice=ast.Constant(index), ctx=ast.Load())


def function_def(source: str) -> ast.FunctionDef:
    """The single function definition of a checked skeleton source."""
    tree = ast.parse(source)
    defs = [n for n in tree.body if isinstance(n, ast.FunctionDef)]
    if len(defs) != 1:
        raise ValueError("expected exactly one function definition")
    return defs[0]


@functools.lru_cache(maxsize=4096)
def split_lines(source: str) -> tuple[tuple[Line, ...], tuple[tuple[int, ...], ...]]:
    """Split a checked skeleton into self-contained output lines.

    Returns the lines and, for each line, the original parameter indices in the order of the
    line's new indices (so ``params[list(mapping[j])]`` are line ``j``'s fitted parameters).
    Memoised by source (the selection splits the same few hundred sources thousands of times):
    the lines are shared, so their expressions are never changed in place (every transform in
    the package works on a copy).
    """
    fn = function_def(source)
    env: dict[str, ast.expr] = {}
    outputs: list[ast.expr] = []
    for stmt in fn.body:
        if isinstance(stmt, ast.Assign):
            value = _Inline(env).visit(copy_tree(stmt.value))
            for target in stmt.targets:
                if isinstance(target, ast.Name):
                    env[target.id] = value
                elif isinstance(target, ast.Tuple) and isinstance(value, ast.Tuple):
                    for t, v in zip(target.elts, value.elts, strict=True):
                        if isinstance(t, ast.Name):
                            env[t.id] = v
                else:
                    raise ValueError(f"cannot split assignment: {ast.unparse(stmt)}")
        elif isinstance(stmt, ast.AugAssign) and isinstance(stmt.target, ast.Name):
            current = env.get(stmt.target.id, ast.Name(stmt.target.id, ast.Load()))
            value = _Inline(env).visit(copy_tree(stmt.value))
            env[stmt.target.id] = ast.BinOp(left=current, op=stmt.op, right=value)
        elif isinstance(stmt, ast.Return) and stmt.value is not None:
            value = _Inline(env).visit(copy_tree(stmt.value))
            outputs = list(value.elts) if isinstance(value, ast.Tuple) else [value]
        elif isinstance(stmt, ast.Expr) and isinstance(stmt.value, ast.Constant):
            continue  # docstring
        else:
            raise ValueError(f"cannot split statement: {ast.unparse(stmt)}")
    lines, mappings = [], []
    for expr in outputs:
        renumber = _Renumber()
        new = renumber.visit(copy_tree(expr))
        ast.fix_missing_locations(new)
        lines.append(Line(new, len(renumber.mapping)))
        mappings.append(tuple(renumber.mapping))
    return tuple(lines), tuple(mappings)


def written_by_name(source: str) -> dict[str, ast.expr] | None:
    """Each output's own expression in a skeleton whose every statement assigns one name (the
    returned outputs read by name in later statements, as a relation among them reads the
    others: ``P_e_ = p[15] * i_q_ * v_q_``), not inlined; None where any other statement or an
    intermediate name that is not returned appears (then only :func:`split_lines` can say
    what an output is)."""
    fn = function_def(source)
    assigned: dict[str, ast.expr] = {}
    returned: list[str] = []
    for stmt in fn.body:
        if (
            isinstance(stmt, ast.Assign) and len(stmt.targets) == 1
            and isinstance(stmt.targets[0], ast.Name)
        ):  # fmt: skip
            assigned[stmt.targets[0].id] = stmt.value
        elif isinstance(stmt, ast.Return) and stmt.value is not None:
            values = stmt.value.elts if isinstance(stmt.value, ast.Tuple) else [stmt.value]
            if not all(isinstance(v, ast.Name) for v in values):
                return None
            returned = [v.id for v in values]  # type: ignore[attr-defined]
        elif not (isinstance(stmt, ast.Expr) and isinstance(stmt.value, ast.Constant)):
            return None
    if set(assigned) != set(returned) or len(returned) != len(assigned):
        return None
    return {name: assigned[name] for name in returned}


def assemble(
    name: str,
    arguments: Sequence[str],
    lines: Sequence[Line],
    outputs: Sequence[str],
    *,
    after: Sequence[str] = (),
    returns: Sequence[str] | None = None,
) -> str:
    """Assemble a skeleton source from lines: one assignment per output, then the statements
    ``after`` (each one line of code that may read those outputs by name, its parameters
    numbered after the lines'), then the return of ``returns`` (default: ``outputs``)."""
    offset = 0
    body: list[str] = []
    for out, line in zip(outputs, lines, strict=True):
        renumber = _Renumber(offset)
        expr = renumber.visit(copy_tree(line.expr))
        # keep every parameter slot of the line even if the renumbering saw fewer
        offset += max(line.n_params, len(renumber.mapping))
        body.append(f"    {out} = {ast.unparse(ast.fix_missing_locations(expr))}")
    used = set().union(*(line.variables() for line in lines)) if lines else set()
    args = [a for a in arguments if a in used]
    header = f"def {name}({', '.join([*args, 'p'])}):"
    body += [f"    {statement}" for statement in after]
    returned = outputs if returns is None else returns
    return "\n".join([header, *body, f"    return {', '.join(returned)}"]) + "\n"


def summands(node: ast.expr) -> list[ast.expr]:
    """The summands of a sum (``a - b`` gives ``a`` and ``-b``); a non-sum is one summand."""
    if isinstance(node, ast.BinOp) and isinstance(node.op, ast.Add | ast.Sub):
        right = node.right
        if isinstance(node.op, ast.Sub):
            right = ast.UnaryOp(op=ast.USub(), operand=right)
        return [*summands(node.left), *summands(right)]
    return [node]


def without_each_summand(line: Line) -> list[Line]:
    """``line`` with one summand left out, for each summand that carries a parameter.

    The parameters of what remains are renumbered from ``p[0]``. A line of one summand, or one
    whose parameters are shared between summands (dropping one would change another), gives
    nothing.
    """
    parts = summands(line.expr)
    if len(parts) < 2:
        return []
    out = []
    for k, part in enumerate(parts):
        if param_indices(part):
            rest = kept_summands(line, [i != k for i in range(len(parts))])
            if rest is not None:
                out.append(rest)
    return out


def kept_summands(line: Line, keep: Sequence[bool]) -> Line | None:
    """``line`` with only the summands ``keep`` marks (one flag per :func:`summands`), its
    parameters renumbered from ``p[0]``; None if no summand with a parameter is kept, or if
    the summands share parameters (dropping one would change another)."""
    parts = summands(line.expr)
    if len(keep) != len(parts):
        raise ValueError(f"{len(keep)} flags for {len(parts)} summands")
    params = [set(param_indices(s)) for s in parts]
    if any(a & b for i, a in enumerate(params) for b in params[i + 1 :]):
        return None
    rest = [copy_tree(s) for s, k in zip(parts, keep, strict=True) if k]
    if not rest:
        return None
    expr = rest[0]
    for s in rest[1:]:
        expr = ast.BinOp(left=expr, op=ast.Add(), right=s)
    renumber = _Renumber()
    expr = ast.fix_missing_locations(renumber.visit(expr))
    return Line(expr, len(renumber.mapping)) if renumber.mapping else None


def simple_summands(line: Line) -> list[Line]:
    """The summands of ``line`` that carry exactly one parameter, each as a line of its own
    (``p[3] * i_q`` gives ``p[0] * i_q``): the terms a line can lend to another."""
    out = []
    for s in summands(line.expr):
        if len(param_indices(s)) != 1:
            continue
        renumber = _Renumber()
        expr = ast.fix_missing_locations(renumber.visit(copy_tree(s)))
        out.append(Line(expr, 1))
    return out


def with_summand(line: Line, term: Line) -> Line:
    """``line + term``, the term's parameters numbered after the line's."""
    renumber = _Renumber(line.n_params)
    extra = renumber.visit(copy_tree(term.expr))
    expr = ast.BinOp(left=copy_tree(line.expr), op=ast.Add(), right=extra)
    return Line(ast.fix_missing_locations(expr), line.n_params + len(renumber.mapping))


def renumbered(line: Line) -> Line:
    """``line`` with its parameters numbered in order of appearance, as :func:`assemble` numbers
    them (so parameters fitted to a skeleton assembled from the line are in the line's order)."""
    renumber = _Renumber()
    expr = ast.fix_missing_locations(renumber.visit(copy_tree(line.expr)))
    return Line(expr, max(line.n_params, len(renumber.mapping)))


def inlined(expr: ast.expr, env: dict[str, ast.expr]) -> ast.expr:
    """``expr`` with each name of ``env`` replaced by (a copy of) its expression."""
    return ast.fix_missing_locations(_Inline(env).visit(copy_tree(expr)))


class _Rename(ast.NodeTransformer):
    def __init__(self, names: dict[str, str]) -> None:
        self.names = names

    def visit_Name(self, node: ast.Name) -> ast.Name:
        return ast.Name(self.names.get(node.id, node.id), node.ctx)


def renamed(expr: ast.expr, names: dict[str, str]) -> ast.expr:
    """(A copy of) ``expr`` with each variable of ``names`` renamed to its value."""
    return ast.fix_missing_locations(_Rename(names).visit(copy_tree(expr)))


def substitute_params(expr: ast.expr, params: Sequence[float], digits: int = 6) -> str:
    """The expression with fitted parameter values in place of ``p[i]`` (for readable output);
    the line's own float constants (a line built from other lines carries their fitted
    parameters as constants) are shown to the same number of significant digits."""

    class _Sub(ast.NodeTransformer):
        def visit_Subscript(self, node: ast.Subscript) -> ast.expr:
            index = param_index(node)
            if index is None:
                return self.generic_visit(node)
            return ast.Constant(float(f"{params[index]:.{digits}g}"))

        def visit_Constant(self, node: ast.Constant) -> ast.expr:
            if isinstance(node.value, float):
                return ast.Constant(float(f"{node.value:.{digits}g}"))
            return node

    new = _Sub().visit(copy_tree(expr))
    return ast.unparse(ast.fix_missing_locations(new))
