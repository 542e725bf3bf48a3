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

The package has one module per job: :mod:`~jaxdmd.skeleton.extraction` (answer text -> source
and requests), :mod:`~jaxdmd.skeleton.checking` (the whitelist check),
:mod:`~jaxdmd.skeleton.compiling` (rewrite, compile, lower, probe) and
:mod:`~jaxdmd.skeleton.core` (limits, ``Skeleton``, ``SkeletonError``); the vocabulary shared
with :mod:`jaxdmd.interp` is :mod:`jaxdmd.whitelist`. Everything is importable from here.
"""

from jaxdmd.skeleton.checking import check
from jaxdmd.skeleton.compiling import (
    MAX_COMPILED_NODES,
    MAX_PROGRAM_INSTRUCTIONS,
    compile_skeleton,
    probe,
    sizes,
    try_compile,
)
from jaxdmd.skeleton.core import (
    ALIASES,
    FUNCTIONS,
    MAX_ANSWER_CHARS,
    MAX_DEPTH,
    MAX_EXPONENT,
    MAX_LITERAL,
    MAX_NODES,
    MAX_PARAMS,
    MAX_SOURCE_CHARS,
    Skeleton,
    SkeletonError,
)
from jaxdmd.skeleton.extraction import extract

__all__ = [
    "ALIASES",
    "FUNCTIONS",
    "MAX_ANSWER_CHARS",
    "MAX_COMPILED_NODES",
    "MAX_DEPTH",
    "MAX_EXPONENT",
    "MAX_LITERAL",
    "MAX_NODES",
    "MAX_PARAMS",
    "MAX_PROGRAM_INSTRUCTIONS",
    "MAX_SOURCE_CHARS",
    "Skeleton",
    "SkeletonError",
    "check",
    "compile_skeleton",
    "extract",
    "probe",
    "sizes",
    "try_compile",
]
