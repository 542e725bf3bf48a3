"""Checked skeletons as register-machine programs, run by one fixed JAX interpreter.

XLA compiles every distinct function anew, and on a CPU that compile (about 0.5 s per candidate,
more with its Jacobian) costs far more than fitting a small model. A checked skeleton uses only a
handful of operations (arithmetic, comparisons, conditional expressions, a few math functions),
so instead of compiling each candidate, :func:`lower` translates its syntax tree into a short
*program* for a register machine, and :func:`run` evaluates any program with the same code: a
loop over the instructions with a ``lax.switch`` on the opcode. A program is data (integer and
float arrays), so one compiled interpreter serves every candidate of every round; differentiating
through :func:`run` (``jax.jvp``) gives exact forward-mode derivatives, the same as differentiating
the compiled skeleton.

A program is straight-line code in SSA form with common subexpressions shared, dead assignments
removed, and registers reused once their value is dead (linear-scan allocation), so the register
file stays small. Each instruction is ``(op, a, b, c, imm) -> dst``: ``a``, ``b``, ``c`` are
registers (or, for ``var``/``param``, the index of the argument or parameter) and ``imm`` a float
immediate (the value of ``const`` and of constant exponents).

Semantics follow ``jaxdmd.skeleton``'s compiled functions: comparisons give 0.0 or 1.0, comparison
chains are conjunctions, ``a if c else b`` is ``where(c, a, b)`` (both evaluated), integer
exponents are expanded into multiplications like ``lax.integer_pow``, other constant exponents
use ``pow`` with a constant (no derivative with respect to the exponent), ``x ** p[i]`` is a
power with a trainable exponent.

:func:`evaluate_numpy` runs a program in NumPy on the host (for the fitter's cheap checks, such as
the test for parameters entering linearly, which would otherwise dispatch JAX operations one by
one) and for the rollouts that choose models by simulation; its values alone run as one
straight-line Python function per program, written from the program's register numbers with the
rules bound by name (a host rollout evaluates small programs at every step, where an interpreter
loop's dispatch would cost more than the arithmetic). Nothing here executes the skeleton's text:
lowering only reads the syntax tree.
"""

from __future__ import annotations

import ast
import contextlib
import dataclasses
import functools
import math
import weakref
from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from jaxdmd import whitelist as wl

__all__ = [
    "OPCODES", "RULES", "LoweringError", "Program", "ProgramTooLarge", "evaluate_numpy", "lower",
    "lowered", "program_of", "run", "run_numpy",
]  # fmt: skip

# opcode name -> number of register operands (var/param/const take an index or an immediate)
OPCODES: tuple[str, ...] = (
    "nop", "var", "param", "const",
    "neg", "add", "sub", "mul", "div", "pow", "powc",
    "sin", "cos", "tan", "exp", "log", "sqrt", "tanh", "sinh", "cosh",
    "arctan", "arcsin", "arccos", "abs", "sign", "square",
    "arctan2", "maximum", "minimum", "where", "clip",
    "lt", "le", "gt", "ge", "eq", "ne", "and",
)  # fmt: skip
OP = {name: i for i, name in enumerate(OPCODES)}
_ARITY = {
    "nop": 0, "var": 0, "param": 0, "const": 0, "neg": 1, "powc": 1,
    "add": 2, "sub": 2, "mul": 2, "div": 2, "pow": 2, "arctan2": 2, "maximum": 2, "minimum": 2,
    "lt": 2, "le": 2, "gt": 2, "ge": 2, "eq": 2, "ne": 2, "and": 2, "where": 3, "clip": 3,
}  # fmt: skip
_UNARY_FUNCTIONS = (
    "sin", "cos", "tan", "exp", "log", "sqrt", "tanh", "sinh", "cosh",
    "arctan", "arcsin", "arccos", "abs", "sign", "square",
)  # fmt: skip
_ARITY.update({f: 1 for f in _UNARY_FUNCTIONS})
_BINOPS = {ast.Add: "add", ast.Sub: "sub", ast.Mult: "mul", ast.Div: "div"}
_CMPOPS = {ast.Lt: "lt", ast.LtE: "le", ast.Gt: "gt", ast.GtE: "ge", ast.Eq: "eq", ast.NotEq: "ne"}
MAX_INSTRUCTIONS = 2048  # of a program after dead-code elimination
MAX_SSA = 2 * MAX_INSTRUCTIONS  # of the SSA code while lowering (before it)


class LoweringError(ValueError):
    """The source uses something the interpreter does not implement (the caller falls back)."""


class ProgramTooLarge(LoweringError):
    """The program exceeds ``MAX_SSA`` or ``MAX_INSTRUCTIONS`` (a size budget, checked while
    lowering: no checked skeleton comes near it)."""


@dataclasses.dataclass(frozen=True, eq=False)
class Program:
    """A lowered skeleton. Arrays are NumPy: ``ops``, ``a``, ``b``, ``c``, ``dst`` int32 ``[L]``,
    ``imm`` float64 ``[L]``, ``outputs`` int32 ``[K]`` (registers holding the outputs).

    ``var`` instructions read rows of ``feature_values`` (the parameter-free subexpressions,
    computed once by the ``features`` program); ``parts`` are the programs of the single outputs,
    each with local parameters ``0 .. n_params-1`` and ``params`` mapping them to ``p``."""

    arguments: tuple[str, ...]
    n_params: int
    ops: np.ndarray
    a: np.ndarray
    b: np.ndarray
    c: np.ndarray
    dst: np.ndarray
    imm: np.ndarray
    outputs: np.ndarray
    n_regs: int
    features: Program | None = None
    parts: tuple[Program, ...] = ()
    params: np.ndarray | None = None
    kinds: np.ndarray | None = None  # [L, 3]: operand from a register (0), row (1), p (2), imm (3)
    consts: np.ndarray | None = None  # [L, 3]: the operands' immediates (kind 3)

    @property
    def length(self) -> int:
        return int(self.ops.shape[0])

    @property
    def n_outputs(self) -> int:
        return int(self.outputs.shape[0])

    def feature_values(self, args: Sequence[np.ndarray]) -> np.ndarray:
        """The rows the program's ``var`` instructions read: ``[F, N]`` (NumPy)."""
        if self.features is None:
            n = np.shape(args[0])[0] if len(args) else 1
            return np.zeros((0, n))
        return evaluate_numpy(self.features, args, np.zeros((1, 1)))[0]

    def values(self, args: Sequence[np.ndarray], p: np.ndarray) -> np.ndarray:
        """Predictions ``[B, K, N]`` at parameters ``p [B, P]`` (NumPy, on the host)."""
        n = np.shape(args[0])[0] if len(args) else 1
        return evaluate_numpy(self, list(self.feature_values(args)), p, n)


# ---------------------------------------------------------------------------------------------
# Lowering: syntax tree -> SSA -> registers


class _Lowerer:
    def __init__(self, arguments: Sequence[str]) -> None:
        self.code: list[tuple[str, int, int, int, float]] = []  # SSA: (op, a, b, c, imm)
        self.memo: dict[tuple[str, int, int, int, float], int] = {}
        self.env: dict[str, int] = {}
        self.arguments = tuple(arguments)
        self.n_params = 0

    def emit(self, op: str, a: int = 0, b: int = 0, c: int = 0, imm: float = 0.0) -> int:
        key = (op, a, b, c, float(imm))
        if op == "const" and math.isnan(imm):  # never produced by a checked skeleton
            raise LoweringError("NaN constant")
        found = self.memo.get(key)
        if found is not None:
            return found
        if len(self.code) >= MAX_SSA:
            raise ProgramTooLarge(f"more than {MAX_SSA} SSA instructions")
        self.code.append(key)
        self.memo[key] = len(self.code) - 1
        return len(self.code) - 1

    def const(self, value: float) -> int:
        return self.emit("const", imm=float(value))

    def statement(self, node: ast.stmt) -> None:
        if isinstance(node, ast.Assign):
            if len(node.targets) == 1 and isinstance(node.targets[0], ast.Tuple | ast.List):
                names = node.targets[0].elts
                if not isinstance(node.value, ast.Tuple | ast.List) or len(node.value.elts) != len(
                    names
                ):
                    raise LoweringError("unpacking")
                values = [self.expr(v) for v in node.value.elts]  # all right-hand sides first
                for target, value in zip(names, values, strict=True):
                    self.env[self.target(target)] = value
            else:
                value = self.expr(node.value)
                for target in node.targets:
                    self.env[self.target(target)] = value
        elif isinstance(node, ast.AugAssign):
            name = self.target(node.target)
            if name not in self.env:
                raise LoweringError(f"{name} updated before assignment")
            self.env[name] = self.binop(node.op, self.env[name], node.value)
        else:
            raise LoweringError(f"statement {type(node).__name__}")

    def target(self, node: ast.expr) -> str:
        if not isinstance(node, ast.Name) or node.id == "p":
            raise LoweringError("assignment target")
        return node.id

    def binop(self, op: ast.operator, left: int, right_node: ast.expr) -> int:
        if isinstance(op, ast.Pow):
            return self.power(left, right_node)
        name = _BINOPS.get(type(op))
        if name is None:
            raise LoweringError(f"operator {type(op).__name__}")
        return self.emit(name, left, self.expr(right_node))

    def power(self, base: int, exponent: ast.expr) -> int:
        value = wl.fold(exponent)
        if value is None:  # p[i] or -p[i]: a trainable exponent
            return self.emit("pow", base, self.expr(exponent))
        if isinstance(value, int) and not isinstance(value, bool):
            return self.integer_power(base, value)
        if not math.isfinite(float(value)):
            raise LoweringError("non-finite exponent")
        return self.emit("powc", base, imm=float(value))

    def integer_power(self, x: int, n: int) -> int:
        """``x ** n`` as ``lax.integer_pow`` computes it (square-and-multiply, then 1/acc)."""
        if n == 0:
            # integer_pow(x, 0) is one everywhere; keep x alive for nothing: a constant
            return self.const(1.0)
        m, acc = abs(n), None
        while True:
            if m & 1:
                acc = x if acc is None else self.emit("mul", acc, x)
            m >>= 1
            if not m:
                break
            x = self.emit("mul", x, x)
        assert acc is not None
        return self.emit("div", self.const(1.0), acc) if n < 0 else acc

    def expr(self, node: ast.expr) -> int:
        if isinstance(node, ast.Constant):
            value = node.value
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise LoweringError("constant")
            return self.const(float(value))
        if isinstance(node, ast.Name):
            if node.id in self.env:
                return self.env[node.id]
            if node.id in wl.BARE_CONSTANTS:
                return self.const(wl.CONSTANTS[node.id])
            raise LoweringError(f"name {node.id}")
        if isinstance(node, ast.Attribute):
            name = wl.math_name(node)
            if name in wl.CONSTANTS:
                return self.const(wl.CONSTANTS[name])
            raise LoweringError("attribute")
        if isinstance(node, ast.Subscript):
            if not wl.is_param(node):
                raise LoweringError("subscript")
            index = node.slice.value  # type: ignore[attr-defined]
            if not isinstance(index, int) or not 0 <= index < wl.MAX_PARAMS:
                raise LoweringError("parameter index")
            self.n_params = max(self.n_params, index + 1)
            return self.emit("param", index)
        if isinstance(node, ast.BinOp):
            return self.binop(node.op, self.expr(node.left), node.right)
        if isinstance(node, ast.UnaryOp):
            if isinstance(node.op, ast.UAdd):
                return self.expr(node.operand)
            if isinstance(node.op, ast.USub):
                return self.emit("neg", self.expr(node.operand))
            raise LoweringError("unary operator")
        if isinstance(node, ast.Compare):
            operands = [self.expr(node.left), *(self.expr(c) for c in node.comparators)]
            result = None
            for x, op, y in zip(operands[:-1], node.ops, operands[1:], strict=True):
                name = _CMPOPS.get(type(op))
                if name is None:
                    raise LoweringError("comparison")
                pair = self.emit(name, x, y)
                result = pair if result is None else self.emit("and", result, pair)
            assert result is not None
            return result
        if isinstance(node, ast.IfExp):
            test, body, orelse = self.expr(node.test), self.expr(node.body), self.expr(node.orelse)
            return self.emit("where", test, body, orelse)
        if isinstance(node, ast.Call):
            func = node.func
            name = func.id if isinstance(func, ast.Name) else wl.math_name(func)
            name = wl.ALIASES.get(name, name) if name is not None else None
            if name not in wl.FUNCTIONS or node.keywords:
                raise LoweringError("call")
            if len(node.args) != wl.FUNCTIONS[name][1]:
                raise LoweringError("arity")
            args = [self.expr(a) for a in node.args]
            return self.emit(name, *args)
        raise LoweringError(f"expression {type(node).__name__}")


def lower(source: str, n_outputs: int | None = None) -> Program:
    """Lower a checked skeleton's source (``Skeleton.source``) to a :class:`Program`.

    Raises :class:`LoweringError` for anything outside the skeleton whitelist.
    """
    try:
        tree = ast.parse(source)
    except (SyntaxError, ValueError, RecursionError) as error:
        raise LoweringError(f"parse: {error}") from None
    functions = [s for s in tree.body if isinstance(s, ast.FunctionDef)]
    if len(functions) != 1 or len(tree.body) != 1:
        raise LoweringError("one function expected")
    fdef = functions[0]
    names = [a.arg for a in fdef.args.args]
    if not names or names[-1] != "p":
        raise LoweringError("last parameter must be p")
    low = _Lowerer(names[:-1])
    for i, name in enumerate(names[:-1]):
        low.env[name] = low.emit("var", i)
    body = list(fdef.body)
    if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant):
        body = body[1:]
    if not body or not isinstance(body[-1], ast.Return) or body[-1].value is None:
        raise LoweringError("the function must end with a return")
    try:
        for statement in body[:-1]:
            low.statement(statement)
        value = body[-1].value
        elements = value.elts if isinstance(value, ast.Tuple | ast.List) else [value]
        outputs = [low.expr(e) for e in elements]
    except RecursionError:
        raise LoweringError("too deep") from None
    if n_outputs is not None and len(outputs) != n_outputs:
        raise LoweringError(f"{len(outputs)} outputs, expected {n_outputs}")
    return _split(low, outputs)


def _split(low: _Lowerer, outputs: list[int]) -> Program:
    """Hoist what does not depend on ``p`` into a feature program, evaluated once per data set.

    The main program then reads those values as rows of its input (``var`` instructions): only
    parameter-dependent instructions are left for the interpreter, which runs them with
    tangents at every LM iteration of every restart.
    """
    code = low.code
    depends = [False] * len(code)
    for i, (op, a, b, c, _) in enumerate(code):
        n = _ARITY[op]
        depends[i] = op == "param" or any(depends[x] for x in (a, b, c)[:n])
    # features: p-independent values read by p-dependent instructions, or returned
    features: list[int] = []
    seen: set[int] = set()

    def feature(x: int) -> None:
        if x not in seen and not depends[x] and code[x][0] != "const":
            seen.add(x)
            features.append(x)

    for i, (op, a, b, c, _) in enumerate(code):
        if depends[i]:
            for x in (a, b, c)[: _ARITY[op]]:
                feature(x)
    for o in outputs:
        feature(o)
    features.sort()
    feature_program = _allocate(low.code, features, low.arguments, 0) if features else None
    row = {x: k for k, x in enumerate(features)}
    main: list[tuple[str, int, int, int, float]] = []
    index: dict[int, int] = {}
    for i, (op, a, b, c, imm) in enumerate(code):
        if i in row:
            main.append(("var", row[i], 0, 0, 0.0))
        elif depends[i] or op == "const":
            if op == "param":
                main.append((op, a, b, c, imm))
            else:
                args = [index.get(x, -1) for x in (a, b, c)[: _ARITY[op]]]
                main.append((op, *args, *([0] * (3 - len(args))), imm))  # type: ignore[arg-type]
        else:
            continue
        index[i] = len(main) - 1
    arguments = tuple(f"f{k}" for k in range(len(features)))
    main_outputs = [index[o] for o in outputs]
    program = _allocate(main, main_outputs, arguments, low.n_params)
    parts = tuple(_output_program(main, o, arguments) for o in main_outputs)
    return dataclasses.replace(
        program, arguments=low.arguments, features=feature_program, parts=parts
    )


def _output_program(
    main: list[tuple[str, int, int, int, float]], output: int, arguments: tuple[str, ...]
) -> Program:
    """The program of one output, with its parameters renumbered 0, 1, ... (``params`` maps
    them back): the Jacobian of an output is only as wide as its own parameters."""
    cone = [False] * len(main)
    cone[output] = True
    for i in range(output, -1, -1):
        if cone[i]:
            op, a, b, c, _ = main[i]
            for x in (a, b, c)[: _ARITY[op]]:
                cone[x] = True
    used = sorted({main[i][1] for i in range(len(main)) if cone[i] and main[i][0] == "param"})
    local = {g: j for j, g in enumerate(used)}
    code = [
        ("param", local[a], b, c, imm) if op == "param" and cone[i] else (op, a, b, c, imm)
        for i, (op, a, b, c, imm) in enumerate(main)
    ]
    program = _allocate(code, [output], arguments, len(used))
    return dataclasses.replace(program, params=np.array(used, dtype=np.int32))


_LEAVES = {"var": 1, "param": 2, "const": 3}  # operand kinds; 0 is a register


def _allocate(
    code: list[tuple[str, int, int, int, float]],
    outputs: list[int],
    arguments: tuple[str, ...],
    n_params: int,
) -> Program:
    """Registers for an SSA code: loads (``var``, ``param``, ``const``) are folded into the
    operands of the instructions that use them (operand kinds), linear-scan allocation."""
    live = [False] * len(code)
    for o in outputs:
        live[o] = True
    for i in range(len(code) - 1, -1, -1):  # dead-code elimination (operands precede users)
        if live[i]:
            op, a, b, c, _ = code[i]
            for j, x in enumerate((a, b, c)):  # a load is folded into its users' operands
                if j < _ARITY[op] and code[x][0] not in _LEAVES:
                    live[x] = True
    order = [i for i in range(len(code)) if live[i]]
    if len(order) > MAX_INSTRUCTIONS:
        raise ProgramTooLarge(f"{len(order)} instructions (limit {MAX_INSTRUCTIONS})")

    def in_register(x: int) -> bool:
        return code[x][0] not in _LEAVES

    last_use: dict[int, int] = {}
    for pos, i in enumerate(order):
        op, a, b, c, _ = code[i]
        for j, x in enumerate((a, b, c)):
            if j < _ARITY[op] and in_register(x):
                last_use[x] = pos
    for o in outputs:
        last_use[o] = len(order)  # outputs stay live to the end
    reg: dict[int, int] = {}
    free: list[int] = []
    n_regs = 0
    rows = []
    for pos, i in enumerate(order):
        op, a, b, c, imm = code[i]
        n = _ARITY[op]
        operands, kinds, consts = [0, 0, 0], [0, 0, 0], [0.0, 0.0, 0.0]
        for j, x in enumerate((a, b, c)[:n]):
            if in_register(x):
                operands[j] = reg[x]
            else:
                leaf, index, _, _, value = code[x]
                kinds[j] = _LEAVES[leaf]
                operands[j] = index if leaf != "const" else 0
                consts[j] = value if leaf == "const" else 0.0
        if op in ("var", "param"):
            operands[0] = a
        for j, x in enumerate((a, b, c)):  # operands dead after this instruction
            if j < n and in_register(x) and last_use.get(x) == pos and reg[x] not in free:
                free.append(reg[x])
        if free:
            free.sort()
            r = free.pop(0)
        else:
            r, n_regs = n_regs, n_regs + 1
        reg[i] = r
        if last_use.get(i) is None:  # never read (cannot happen after DCE, but be safe)
            free.append(r)
        rows.append((OP[op], *operands, r, imm, kinds, consts))
    arr = np.array([row[:5] for row in rows], dtype=np.int32).reshape(-1, 5)
    return Program(
        arguments=arguments,
        n_params=n_params,
        ops=arr[:, 0].copy(),
        a=arr[:, 1].copy(),
        b=arr[:, 2].copy(),
        c=arr[:, 3].copy(),
        dst=arr[:, 4].copy(),
        imm=np.array([row[5] for row in rows], dtype=np.float64),
        outputs=np.array([reg[o] for o in outputs], dtype=np.int32),
        n_regs=max(1, n_regs),
        kinds=np.array([row[6] for row in rows], dtype=np.int32).reshape(-1, 3),
        consts=np.array([row[7] for row in rows], dtype=np.float64).reshape(-1, 3),
    )


# Programs of compiled skeletons, keyed by the function object compile_skeleton made from the
# source: a skeleton whose ``fn`` was replaced (dataclasses.replace) has no program and is fitted
# through its own function instead.
_SOURCES: weakref.WeakKeyDictionary[Callable[..., Any], str] = weakref.WeakKeyDictionary()


def register(fn: Callable[..., Any], source: str) -> None:
    """Record that ``fn`` was compiled from ``source`` (called by ``jaxdmd.skeleton``)."""
    with contextlib.suppress(TypeError):  # not weak-referenceable
        _SOURCES[fn] = source


@functools.lru_cache(maxsize=4096)
def _lower_cached(source: str) -> Program | None:
    try:
        return lower(source)
    except LoweringError:
        return None


def lowered(source: str) -> Program | None:
    """``lower(source)``, cached, or None where it raises :class:`LoweringError`."""
    return _lower_cached(source)


def program_of(skeleton: Any) -> Program | None:
    """The program of a skeleton made by ``compile_skeleton``, else None (fall back to ``fn``)."""
    try:
        source = _SOURCES.get(skeleton.fn)
    except TypeError:
        return None
    if source is None or source != skeleton.source:
        return None
    program = _lower_cached(source)
    if program is None or program.arguments != tuple(skeleton.arguments):
        return None
    if program.n_outputs != int(skeleton.n_outputs) or program.n_params != int(skeleton.n_params):
        return None
    return program


# ---------------------------------------------------------------------------------------------
# NumPy evaluation (host)


def evaluate_numpy(
    program: Program, args: Sequence[np.ndarray], p: np.ndarray, n: int | None = None
) -> np.ndarray:
    """Evaluate on the host: ``args`` one ``[N]`` array per argument, ``p`` ``[B, P]``.

    Returns ``[B, K, N]`` float64 (non-finite values as they come, no warnings). ``n`` is
    needed when there are no ``args``.
    """
    p = np.atleast_2d(np.asarray(p, dtype=np.float64))
    if n is None:
        n = np.shape(args[0])[0] if len(args) else 1
    rows = [np.asarray(x, dtype=np.float64) for x in args]
    with np.errstate(all="ignore"):
        values = _value_function(program)(rows, p)
    out = np.empty((p.shape[0], program.n_outputs, n))
    for j, v in enumerate(values):
        out[:, j, :] = v
    return out


def pointwise_numpy(program: Program, args: Sequence[np.ndarray], p: np.ndarray) -> np.ndarray:
    """Evaluate on the host at ``B`` points, each with its own parameter row: ``args`` one
    ``[B]`` array per argument, ``p`` ``[B, P]``. Returns ``[B, K]``: the diagonal of
    :meth:`Program.values` (point b at row b), computed without the ``[B, K, B]`` outer
    product (the same rules on the same numbers, so the same values to the bit)."""
    p = np.atleast_2d(np.asarray(p, dtype=np.float64))
    b = p.shape[0]
    with np.errstate(all="ignore"):
        rows = _feature_rows(program, args, np.shape(args[0])[0] if len(args) else b)
        # a parameter slice of [1, P, B] is [1, 1, B]: it broadcasts against a row's [1, B]
        values = _value_function(program)(rows, p.T[None])
    out = np.empty((b, program.n_outputs))
    for j, v in enumerate(values):  # v is [1, 1, B] or [1, B], or one number for every point
        out[:, j] = np.reshape(v, -1)
    return out


_NO_PARAMS = np.zeros((1, 1))  # the features' program reads no parameter


def _feature_rows(program: Program, args: Sequence[np.ndarray], n: int) -> list[np.ndarray]:
    """The rows of :meth:`Program.feature_values` as a list of ``[n]`` arrays, without packing
    them into one array and out again (the same values: the features' program on the same
    arguments). Call inside ``np.errstate(all="ignore")``."""
    if program.features is None:
        return []
    values = _value_function(program.features)(
        [np.asarray(x, dtype=np.float64) for x in args], _NO_PARAMS
    )
    return [
        v[0] if np.shape(v) == (1, n) else np.broadcast_to(v, (1, n))[0].astype(np.float64)
        for v in values
    ]


def run_numpy(
    program: Program, rows: np.ndarray, q: np.ndarray, tangents: bool = True, careful: bool = True
) -> tuple[list[Any], list[Any]]:
    """Run a program with forward-mode derivatives on the host: the NumPy twin of :func:`run`.

    ``rows`` ``[F, N]`` are the rows ``var`` instructions read, ``q`` ``[R, P]`` the parameters
    (one row per restart). Returns, per output, its value (broadcastable to ``[R, N]``) and its
    tangent (broadcastable to ``[R, P, N]``; None where it does not depend on ``q``, or for every
    output when ``tangents`` is False). Values stay as small as their dependence allows (a
    parameter times a row is ``[R, N]``, its tangent ``[1, P, N]``), and an identically zero
    partial derivative skips the operand's tangent, as in :func:`run`.

    ``careful``: a zero partial derivative times an infinite tangent entry (or the reverse) gives
    0, as in :func:`run`; without it such a product is NaN. The two agree wherever the result
    is finite (a non-finite product can only vanish through a structural zero, which both
    skip), so a caller may run without care and again with it only when a tangent is not
    finite. Call inside ``np.errstate(all="ignore")``: non-finite trial points warn otherwise.
    """
    n_p = q.shape[1]
    basis = np.eye(n_p)[:, None, :, None]  # basis[j]: the tangent [1, P, 1] of q[:, j]
    val: list[Any] = [None] * program.n_regs
    tan: list[Any] = [None] * program.n_regs

    def operand(kind: int, index: int, value: float) -> tuple[Any, Any]:
        if kind == 0:
            return val[index], tan[index]
        if kind == 1:
            return rows[index][None, :], None
        if kind == 2:
            return q[:, index : index + 1], basis[index] if tangents else None
        return value, None

    for rule, operands, imm, dst in _host_code(program):
        if rule is None:  # a load
            v, t = operand(*operands[0])
        else:
            value, partials = rule
            ops = [operand(*o) for o in operands]
            xs = [x for x, _ in ops]
            v = value(np, *xs, imm)
            t = None
            if tangents and any(tx is not None for _, tx in ops):
                for dx, (_, tx) in zip(partials(np, *xs, imm, v), ops, strict=False):
                    if dx is not None and tx is not None:
                        term = _chain(dx, tx, careful)
                        t = term if t is None else t + term
        val[dst], tan[dst] = v, t
    outputs = program.outputs.tolist()
    return [val[r] for r in outputs], [tan[r] for r in outputs]


@functools.lru_cache(maxsize=4096)
def _host_code(program: Program) -> list[tuple[Any, tuple[tuple[int, int, Any], ...], Any, int]]:
    """The program decoded once for :func:`run_numpy`: ``(rule, operands, imm, dst)`` per
    instruction, ``rule`` None for a load (``var``, ``param``, ``const``) and each operand
    ``(kind, index, constant)``; three operands for every rule, so that a rule's unused operands
    are filled (with the number 0)."""
    code = []
    for op, a, b, c, d, imm, kinds, consts in zip(
        program.ops.tolist(), program.a.tolist(), program.b.tolist(), program.c.tolist(),
        program.dst.tolist(), program.imm.tolist(), program.kinds.tolist(),
        program.consts.tolist(), strict=True,
    ):  # fmt: skip
        name = OPCODES[op]
        if name in _LEAVES:
            code.append((None, ((_LEAVES[name], a, np.float64(imm)),), imm, d))
            continue
        arity = _ARITY[name]
        operands = tuple(
            (k, i, np.float64(x)) if j < arity else (3, 0, np.float64(0.0))
            for j, (k, i, x) in enumerate(zip(kinds, (a, b, c), consts, strict=True))
        )
        code.append((RULES[name], operands, np.float64(imm), d))
    return code


@functools.lru_cache(maxsize=4096)
def _value_function(program: Program) -> Callable[[list[np.ndarray], np.ndarray], tuple[Any, ...]]:
    """The values alone, as :func:`run_numpy` computes them (the same rules on the same arrays)
    but as one straight-line Python function per program, since a host rollout evaluates small
    programs at every step and an interpreter loop's dispatch costs more than the arithmetic.
    The function's text is made here from register numbers and names of this module's own: the
    rules and constants are bound by name in its namespace (the five arithmetic operators
    written out, :data:`_INFIX`), nothing of a skeleton's text is in it (so what runs is the
    program's instructions, as in :func:`run_numpy`)."""
    namespace: dict[str, Any] = {"np": np, "__builtins__": {}}
    head: dict[str, str] = {}  # a row's or a parameter's view, made once per call, not per use
    body = []
    for j, (rule, operands, imm, dst) in enumerate(_host_code(program)):
        xs = []
        for m, (kind, index, value) in enumerate(operands):
            if kind == 0:
                xs.append(f"r{int(index)}")
            elif kind == 1:
                i = int(index)
                head.setdefault(f"v{i}", f"rows[{i}][None, :]")
                xs.append(f"v{i}")
            elif kind == 2:
                i = int(index)
                head.setdefault(f"q{i}", f"p[:, {i}:{i + 1}]")
                xs.append(f"q{i}")
            else:
                namespace[f"c{j}_{m}"] = value
                xs.append(f"c{j}_{m}")
        infix = _INFIX.get(id(rule))
        if rule is None:
            body.append(f"    r{int(dst)} = {xs[0]}")
        elif infix is not None:  # the rule's own expression, written out: the same operation
            body.append(f"    r{int(dst)} = " + infix.format(*xs))
        else:
            namespace[f"f{j}"], namespace[f"i{j}"] = rule[0], imm
            body.append(f"    r{int(dst)} = f{j}(np, {', '.join(xs)}, i{j})")
    outputs = "".join(f"r{int(r)}, " for r in program.outputs.tolist())
    views = [f"    {name} = {view}" for name, view in head.items()]
    text = "\n".join(["def values(rows, p):", *views, *body, f"    return ({outputs})"])
    exec(compile(text, "<jaxdmd.interp program>", "exec"), namespace)
    return namespace["values"]


def _chain(partial: Any, tangent: np.ndarray, careful: bool) -> np.ndarray:
    """``partial * tangent`` with the partial ``[R|1, N|1]`` (or a number) over the tangent's
    parameter axis; ``careful``: a zero factor gives 0 even against an infinite one."""
    if np.ndim(partial) == 0:
        if partial == 1.0:
            return tangent
    else:
        partial = partial[:, None, :]
    term = partial * tangent
    if careful and not np.all(np.isfinite(term)):  # a number too: x / 0 has the partial inf
        term = np.where((partial == 0) | (tangent == 0), 0.0, term)
    return term


# ---------------------------------------------------------------------------------------------
# Derivative rules, one table for NumPy and JAX


def _balanced(xp: Any, x: Any, ans: Any, y: Any) -> Any:
    """d max(x, y) / dx as JAX defines it: 1 where x wins, 1/2 at ties, else 0."""
    return xp.where(x == ans, 1.0, 0.0) / xp.where(y == ans, 2.0, 1.0)


# (value, partials): value(xp, x, y, z, imm) and partials(xp, x, y, z, imm, value) -> (dx, dy,
# dz), each an array, a number, or None where it is identically zero (the operand's tangent is
# then not read: JAX's symbolic zeros). ``xp`` is numpy or jax.numpy. The rules are JAX's own
# (``jax.lax``'s JVPs), so that both interpreters agree with ``jax.jvp`` of the compiled skeleton.
_Rule = tuple[Callable[..., Any], Callable[..., tuple[Any, Any, Any]]]


def _unary(value: str, partial: Callable[..., Any]) -> _Rule:
    return (
        lambda xp, x, y, z, imm: getattr(xp, value)(x),
        lambda xp, x, y, z, imm, v: (partial(xp, x, v), None, None),
    )


def _compare(fn: Callable[[Any, Any, Any], Any]) -> _Rule:
    return (
        lambda xp, x, y, z, imm: xp.asarray(fn(xp, x, y), dtype=xp.float64),
        lambda xp, x, y, z, imm, v: (None, None, None),
    )


def _clip_partials(xp: Any, x: Any, y: Any, z: Any, imm: Any, v: Any) -> tuple[Any, Any, Any]:
    m = xp.maximum(y, x)
    dm = _balanced(xp, m, v, z)
    return dm * _balanced(xp, x, m, y), dm * _balanced(xp, y, m, x), _balanced(xp, z, v, m)


def _power(xp: Any, x: Any, y: Any) -> Any:
    """``x ** y`` as C99's ``pow`` defines it, on both sides: NumPy's ``power`` takes a
    shortcut for a scalar exponent of 0.5 (a square root, so that ``(-inf) ** 0.5`` is nan and
    ``(-0.0) ** 0.5`` is -0.0, where ``pow`` and XLA give inf and 0.0); ``float_power`` calls
    ``pow`` itself."""
    return np.float_power(x, y) if xp is np else xp.power(x, y)


RULES: dict[str, _Rule] = {
    "neg": (lambda xp, x, y, z, imm: -x, lambda xp, x, y, z, imm, v: (-1.0, None, None)),
    "add": (lambda xp, x, y, z, imm: x + y, lambda xp, x, y, z, imm, v: (1.0, 1.0, None)),
    "sub": (lambda xp, x, y, z, imm: x - y, lambda xp, x, y, z, imm, v: (1.0, -1.0, None)),
    "mul": (lambda xp, x, y, z, imm: x * y, lambda xp, x, y, z, imm, v: (y, x, None)),
    "div": (
        lambda xp, x, y, z, imm: x / y,
        lambda xp, x, y, z, imm, v: (1.0 / y, -x / (y * y), None),
    ),
    "pow": (
        lambda xp, x, y, z, imm: _power(xp, x, y),
        lambda xp, x, y, z, imm, v: (
            y * _power(xp, x, y - 1.0),
            xp.log(xp.where(x == 0, 1.0, x)) * v,
            None,
        ),
    ),
    "powc": (
        lambda xp, x, y, z, imm: _power(xp, x, imm),
        lambda xp, x, y, z, imm, v: (
            xp.where(imm == 0, 0.0, imm * _power(xp, x, imm - 1.0)),
            None,
            None,
        ),
    ),
    "sin": _unary("sin", lambda xp, x, v: xp.cos(x)),
    "cos": _unary("cos", lambda xp, x, v: -xp.sin(x)),
    "tan": _unary("tan", lambda xp, x, v: 1.0 + v * v),
    "exp": _unary("exp", lambda xp, x, v: v),
    "log": _unary("log", lambda xp, x, v: 1.0 / x),
    "sqrt": _unary("sqrt", lambda xp, x, v: 0.5 / v),
    "tanh": _unary("tanh", lambda xp, x, v: 1.0 - v * v),
    "sinh": _unary("sinh", lambda xp, x, v: xp.cosh(x)),
    "cosh": _unary("cosh", lambda xp, x, v: xp.sinh(x)),
    "arctan": _unary("arctan", lambda xp, x, v: 1.0 / (1.0 + x * x)),
    "arcsin": _unary("arcsin", lambda xp, x, v: 1.0 / xp.sqrt(1.0 - x * x)),
    "arccos": _unary("arccos", lambda xp, x, v: -1.0 / xp.sqrt(1.0 - x * x)),
    "abs": _unary("abs", lambda xp, x, v: xp.where(x >= 0, 1.0, -1.0)),
    "sign": _unary("sign", lambda xp, x, v: None),
    "square": _unary("square", lambda xp, x, v: 2.0 * x),
    "arctan2": (
        lambda xp, x, y, z, imm: xp.arctan2(x, y),
        lambda xp, x, y, z, imm, v: (y / (x * x + y * y), -x / (x * x + y * y), None),
    ),
    "maximum": (
        lambda xp, x, y, z, imm: xp.maximum(x, y),
        lambda xp, x, y, z, imm, v: (_balanced(xp, x, v, y), _balanced(xp, y, v, x), None),
    ),
    "minimum": (
        lambda xp, x, y, z, imm: xp.minimum(x, y),
        lambda xp, x, y, z, imm, v: (_balanced(xp, x, v, y), _balanced(xp, y, v, x), None),
    ),
    "where": (
        lambda xp, x, y, z, imm: xp.where(x != 0, y, z),
        lambda xp, x, y, z, imm, v: (
            None,
            xp.asarray(x != 0, dtype=xp.float64),
            xp.asarray(x == 0, dtype=xp.float64),
        ),
    ),
    "clip": (lambda xp, x, y, z, imm: xp.minimum(z, xp.maximum(y, x)), _clip_partials),
    "lt": _compare(lambda xp, x, y: x < y),
    "le": _compare(lambda xp, x, y: x <= y),
    "gt": _compare(lambda xp, x, y: x > y),
    "ge": _compare(lambda xp, x, y: x >= y),
    "eq": _compare(lambda xp, x, y: x == y),
    "ne": _compare(lambda xp, x, y: x != y),
    "and": _compare(lambda xp, x, y: (x != 0) & (y != 0)),
}

# rules that are one arithmetic operator, written out in :func:`_value_function`'s text (the
# rule's own expression on the same operands: the same values to the bit, without a call)
_INFIX = {
    id(RULES["neg"]): "-{0}",
    id(RULES["add"]): "{0} + {1}",
    id(RULES["sub"]): "{0} - {1}",
    id(RULES["mul"]): "{0} * {1}",
    id(RULES["div"]): "{0} / {1}",
}


# ---------------------------------------------------------------------------------------------
# The JAX interpreter (forward mode by hand)


def _dual_branches() -> list[Callable[..., tuple[jax.Array, ...]]]:
    """One function per opcode: ``(x, y, z, imm, i, X, p) -> (value, dx, dy, dz)`` on ``[R, N]``
    (``p`` is ``[R, P]``, ``X`` ``[F, N]``): the value and its partial derivatives with respect
    to the three operands, from :data:`RULES` (zeros where a rule has none)."""

    def branch(rule: _Rule) -> Callable[..., tuple[jax.Array, ...]]:
        value, partials = rule

        def f(x, y, z, imm, i, X, p):
            v = value(jnp, x, y, z, imm)
            ds = partials(jnp, x, y, z, imm, v)
            return v, *(
                jnp.zeros_like(x) if d is None else jnp.broadcast_to(d, x.shape).astype(x.dtype)
                for d in ds
            )

        return f

    def leaf(value: Callable[..., jax.Array]) -> Callable[..., tuple[jax.Array, ...]]:
        def f(x, y, z, imm, i, X, p):
            zero = jnp.zeros_like(x)
            return value(x, imm, i, X, p), zero, zero, zero

        return f

    table = {
        "nop": leaf(lambda x, imm, i, X, p: x),
        "var": leaf(lambda x, imm, i, X, p: jnp.broadcast_to(X[i][None, :], x.shape)),
        "param": leaf(lambda x, imm, i, X, p: jnp.broadcast_to(p[:, i][:, None], x.shape)),
        "const": leaf(lambda x, imm, i, X, p: jnp.broadcast_to(imm, x.shape)),
        **{name: branch(rule) for name, rule in RULES.items()},
    }
    return [table[name] for name in OPCODES]


_BRANCHES = _dual_branches()


def run(
    code: dict[str, jax.Array], X: jax.Array, p: jax.Array, n_regs: int
) -> tuple[jax.Array, jax.Array]:
    """Run one program with forward-mode derivatives, for one or several parameter vectors.

    ``code`` holds the padded arrays ``ops a b c dst imm [L]``, ``outputs [K]`` and ``length``
    (scalar); ``X`` ``[F, N]`` the rows the ``var`` instructions read (padded), ``p`` ``[P]`` or
    ``[R, P]`` (restarts). Returns the outputs ``[(R,) K, N]`` and their Jacobian
    ``[(R,) K, P, N]`` with respect to ``p``.

    Each instruction computes its value and the partial derivatives with respect to its operands
    (in the ``lax.switch``, on ``[R, N]``), then the tangent ``[R, P, N]`` as the chain rule's sum.
    A tangent entry that is exactly zero contributes nothing whatever the partial derivative
    (like JAX's symbolic zeros: ``sqrt`` of a parameter-free 0 does not give ``inf * 0``), and
    a zero partial derivative ignores the operand's tangent (``where`` and unused operands).
    The restarts are a plain array dimension (not ``vmap``), so the opcode stays a scalar and the
    switch runs one branch.
    """
    if p.ndim == 1:
        val, tan = run(code, X, p[None], n_regs)
        return val[0], tan[0]
    n_r, n_p = p.shape
    n = X.shape[1]
    val = jnp.zeros((n_regs, n_r, n), dtype=p.dtype)
    tan = jnp.zeros((n_regs, n_r, n_p, n), dtype=p.dtype)
    basis = jnp.eye(n_p, dtype=p.dtype)
    param = OP["param"]

    n_rows = X.shape[0]

    def operand(val, tan, kind, index, value):
        """An operand's value [R, N] and tangent [R, P, N] from a register, a row, p or imm."""
        reg = jnp.minimum(index, n_regs - 1)
        v = jnp.where(
            kind == 0,
            val[reg],
            jnp.where(
                kind == 1,
                X[jnp.minimum(index, n_rows - 1)][None, :],
                jnp.where(kind == 2, p[:, jnp.minimum(index, n_p - 1)][:, None], value),
            ),
        )
        unit = basis[jnp.minimum(index, n_p - 1)][None, :, None]
        t = jnp.where(kind == 0, tan[reg], jnp.where(kind == 2, unit, 0.0))
        return jnp.broadcast_to(v, (n_r, n)), t

    def body(k, carry):
        val, tan = carry
        op, a, b, c = code["ops"][k], code["a"][k], code["b"][k], code["c"][k]
        kinds, consts = code["kinds"][k], code["consts"][k]
        (x, tx), (y, ty), (z, tz) = (
            operand(val, tan, kinds[j], r, consts[j]) for j, r in enumerate((a, b, c))
        )
        v, dx, dy, dz = lax.switch(op, _BRANCHES, x, y, z, code["imm"][k], a, X, p)
        t = jnp.zeros((n_r, n_p, n), dtype=p.dtype)
        for d, tr in ((dx, tx), (dy, ty), (dz, tz)):
            t = t + jnp.where((d == 0)[:, None, :] | (tr == 0), 0.0, d[:, None, :] * tr)
        unit = jnp.broadcast_to(basis[jnp.minimum(a, n_p - 1)][None, :, None], t.shape)
        t = jnp.where(op == param, unit, t)
        dst = code["dst"][k]
        return (
            lax.dynamic_update_index_in_dim(val, v, dst, 0),
            lax.dynamic_update_index_in_dim(tan, t, dst, 0),
        )

    val, tan = lax.fori_loop(0, code["length"], body, (val, tan))
    outputs = code["outputs"]
    return jnp.swapaxes(val[outputs], 0, 1), jnp.swapaxes(tan[outputs], 0, 1)


def pack(
    programs: Sequence[Program], offsets: Sequence[int], length: int, n_slots: int
) -> dict[str, np.ndarray]:
    """Stack programs into padded arrays ``[n_slots, length]`` (empty slots have length 0), with
    the rows of ``var`` instructions shifted by each program's offset in the stacked rows."""
    k = programs[0].n_outputs
    out = {
        "ops": np.zeros((n_slots, length), np.int32),
        "a": np.zeros((n_slots, length), np.int32),
        "b": np.zeros((n_slots, length), np.int32),
        "c": np.zeros((n_slots, length), np.int32),
        "dst": np.zeros((n_slots, length), np.int32),
        "imm": np.zeros((n_slots, length), np.float64),
        "kinds": np.zeros((n_slots, length, 3), np.int32),
        "consts": np.zeros((n_slots, length, 3), np.float64),
        "outputs": np.zeros((n_slots, k), np.int32),
        "length": np.zeros((n_slots,), np.int32),
    }
    var = OP["var"]
    for s, (prog, offset) in enumerate(zip(programs, offsets, strict=True)):
        n = prog.length
        abc = [prog.a.copy(), prog.b.copy(), prog.c.copy()]
        abc[0][prog.ops == var] += offset
        for j in range(3):
            abc[j][prog.kinds[:, j] == 1] += offset
        for name, arr in (("ops", prog.ops), ("a", abc[0]), ("b", abc[1]), ("c", abc[2]),
                          ("dst", prog.dst), ("imm", prog.imm), ("kinds", prog.kinds),
                          ("consts", prog.consts)):  # fmt: skip
            out[name][s, :n] = arr
        out["outputs"][s] = prog.outputs
        out["length"][s] = n
    return out


def bucket(n: int, smallest: int) -> int:
    """The next power of two >= max(n, smallest)."""
    return max(smallest, 1 << max(0, int(n) - 1).bit_length())
