"""The skeleton whitelist's vocabulary, shared by the checker/compiler and the interpreter.

:mod:`jaxdmd.skeleton` checks and compiles skeletons, :mod:`jaxdmd.interp` lowers the checked
source to register-machine programs, and :mod:`jaxdmd.data` refuses channel names that a
skeleton could not use as variables. All three read the names here (the allowed math functions,
their aliases, the namespaces and constants, the reserved names) and the three small syntax
helpers below, so that neither of the first two imports the other for them.
"""

from __future__ import annotations

import ast
import keyword
import math
from collections.abc import Callable
from typing import Any

import jax.numpy as jnp

__all__ = [
    "ALIASES",
    "BARE_CONSTANTS",
    "CONSTANTS",
    "FUNCTIONS",
    "MAX_PARAMS",
    "NAMESPACES",
    "RESERVED",
    "fold",
    "invalid_variable_name",
    "is_param",
    "math_name",
]

MAX_PARAMS = 64  # p[0] ... p[63]: five state equations of up to a dozen terms each

# The math functions a skeleton may call: name -> (jax.numpy function, number of arguments).
FUNCTIONS: dict[str, tuple[Callable[..., Any], int]] = {
    "sin": (jnp.sin, 1),
    "cos": (jnp.cos, 1),
    "tan": (jnp.tan, 1),
    "exp": (jnp.exp, 1),
    "log": (jnp.log, 1),
    "sqrt": (jnp.sqrt, 1),
    "tanh": (jnp.tanh, 1),
    "sinh": (jnp.sinh, 1),
    "cosh": (jnp.cosh, 1),
    "arctan": (jnp.arctan, 1),
    "arcsin": (jnp.arcsin, 1),
    "arccos": (jnp.arccos, 1),
    "arctan2": (jnp.arctan2, 2),
    "abs": (jnp.abs, 1),
    "sign": (jnp.sign, 1),
    "square": (jnp.square, 1),
    "maximum": (jnp.maximum, 2),
    "minimum": (jnp.minimum, 2),
    "where": (jnp.where, 3),
    "clip": (jnp.clip, 3),
}
# Other spellings of the same functions (Python's math module, numpy).
ALIASES: dict[str, str] = {
    "atan": "arctan",
    "asin": "arcsin",
    "acos": "arccos",
    "atan2": "arctan2",
    "fabs": "abs",
    "absolute": "abs",
}
CONSTANTS: dict[str, float] = {"pi": math.pi, "e": math.e}  # as attributes: jnp.pi, math.e
BARE_CONSTANTS = frozenset({"pi"})  # as bare names (a bare `e` is too easily a variable)
NAMESPACES = frozenset({"jnp", "np", "numpy", "math"})
# Names a skeleton's variables and locals may not take: p, the namespaces, the math names.
RESERVED = frozenset({"p", "jax", *NAMESPACES, *FUNCTIONS, *ALIASES, *BARE_CONSTANTS})


def invalid_variable_name(name: object) -> str | None:
    """Why ``name`` cannot be a skeleton variable (a data channel), or None if it can.

    A variable must be an ASCII Python identifier, not a keyword (``lambda``, ``None``), not
    start with an underscore (``__class__``), and not be a reserved name (``p``, a namespace such
    as ``jnp``, a math function such as ``sin``, or ``pi``).
    """
    if not isinstance(name, str):
        return f"it is a {type(name).__name__}, not a string"
    if not name.isidentifier() or not name.isascii():
        # non-ASCII identifiers are NFKC-normalised by the parser: the code would use another name
        return "it is not a Python identifier of ASCII letters, digits and _ (no leading digit)"
    if keyword.iskeyword(name):
        return "it is a Python keyword"
    if name.startswith("_"):
        return "it starts with an underscore"
    if name in RESERVED:
        return "it is reserved in skeletons (p, a math namespace, function or constant)"
    return None


def math_name(node: ast.expr) -> str | None:
    """``jnp.X``, ``np.X``, ``numpy.X``, ``math.X`` or ``jax.numpy.X``: returns ``X``."""
    if not isinstance(node, ast.Attribute):
        return None
    base = node.value
    if isinstance(base, ast.Name) and base.id in NAMESPACES:
        return node.attr
    if (
        isinstance(base, ast.Attribute)
        and base.attr == "numpy"
        and isinstance(base.value, ast.Name)
        and base.value.id == "jax"
    ):
        return node.attr
    return None


def is_param(node: ast.expr) -> bool:
    """Whether ``node`` is ``p[...]``."""
    return (
        isinstance(node, ast.Subscript)
        and isinstance(node.value, ast.Name)
        and node.value.id == "p"
    )


def fold(node: ast.expr) -> float | int | None:
    """The value of a constant made of numeric literals and + - * /, else None."""
    if isinstance(node, ast.Constant):
        value = node.value
        ok = isinstance(value, int | float) and not isinstance(value, bool)
        return value if ok else None
    if isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.USub | ast.UAdd):
        value = fold(node.operand)
        if value is None:
            return None
        return -value if isinstance(node.op, ast.USub) else value
    if isinstance(node, ast.BinOp) and isinstance(node.op, ast.Add | ast.Sub | ast.Mult | ast.Div):
        left, right = fold(node.left), fold(node.right)
        if left is None or right is None:
            return None
        left, right = float(left), float(right)  # never Python big-integer arithmetic
        try:
            if isinstance(node.op, ast.Add):
                return left + right
            if isinstance(node.op, ast.Sub):
                return left - right
            if isinstance(node.op, ast.Mult):
                return left * right
            return left / right
        except (ZeroDivisionError, OverflowError):
            return math.nan
    return None
