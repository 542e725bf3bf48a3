"""Skeletons' limits, the error type and the compiled-skeleton type (see :mod:`jaxdmd.skeleton`)."""

from __future__ import annotations

import ast
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxdmd import whitelist
from jaxdmd.whitelist import ALIASES, FUNCTIONS, MAX_PARAMS

__all__ = [
    "ALIASES",
    "FUNCTIONS",
    "MAX_ANSWER_CHARS",
    "MAX_DEPTH",
    "MAX_EXPONENT",
    "MAX_LITERAL",
    "MAX_NODES",
    "MAX_PARAMS",
    "MAX_SOURCE_CHARS",
    "Skeleton",
    "SkeletonError",
]

MAX_ANSWER_CHARS = 100_000  # a whole model answer
MAX_SOURCE_CHARS = 4_000  # the extracted function
MAX_NODES = 600  # syntax-tree nodes of the function, without Load/Store markers
MAX_DEPTH = 50  # nesting of the syntax tree, counted from the module
MAX_LITERAL = 1e6  # largest magnitude of a numeric literal
MAX_EXPONENT = 8  # largest magnitude of a constant exponent

# The vocabulary (FUNCTIONS, ALIASES, constants, namespaces, reserved names) lives in
# jaxdmd.whitelist, which jaxdmd.interp reads too.
_CONSTANTS = whitelist.CONSTANTS
_BARE_CONSTANTS = whitelist.BARE_CONSTANTS
_NAMESPACES = whitelist.NAMESPACES
_RESERVED = whitelist.RESERVED
_math_name = whitelist.math_name
_is_param = whitelist.is_param
_fold = whitelist.fold


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


def _parse(source: str) -> ast.Module:
    """``ast.parse`` without its SyntaxWarnings (such as "invalid decimal literal")."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return ast.parse(source, mode="exec")


def _count_nodes(nodes: Sequence[ast.AST]) -> int:
    return sum(
        1 for root in nodes for node in ast.walk(root) if not isinstance(node, ast.expr_context)
    )
