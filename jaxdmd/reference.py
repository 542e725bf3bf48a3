"""Equations that do not depend on where the network puts angle zero.

A component with a frame of its own (a rotor angle among its states) driven at its terminal
(its terminal voltage's magnitude and angle played in: a boundary channel in ``rad``) sees the
rest of the network only through that phasor, and the network's angle reference is
arbitrary: shift every angle the component knows (its rotor angle and the terminal angle) by
the same constant and it does the same thing. Its currents, voltages and powers in its own
frame (d and q axes, magnitudes, powers) and the rates of change of its states do not move;
``V sin(delta - theta)`` does not, ``delta`` alone or ``cos(delta)`` does. A term that moves
with the reference is a stand-in: on the training recordings the rotor angle drifts with what
the term stands in for (on Table I's generator 31 seed 2, ``delta`` in four algebraic lines,
each with a small coefficient), and on another fault, or with the reference elsewhere, it
does not.

So each line of the state equations and of the algebraic variables keeps only the summands
that are reference-free (:func:`reference_free_line`). The test is numerical: a summand, its
parameters set to one, is evaluated on recorded samples with every angle as recorded and with
every angle shifted by each of :data:`SHIFTS`; it is reference-free if its value does not
move beyond round-off. Nothing here knows which variable is which beyond its unit (``rad``)
and its role: where no angle is a state, or none a boundary channel (a machine against an
infinite bus whose angle is the reference, unrecorded), an angle alone is a legitimate term
and nothing is left out. The component's other channels are taken to be in its own frame, as
a machine's d- and q-axis currents and voltages are: a current recorded in the network's
frame (its real and imaginary parts) moves with the reference, and its line would lose the
terms that say so (the run says which terms it leaves out).
"""

from __future__ import annotations

import ast
from collections.abc import Mapping, Sequence

import numpy as np

from jaxdmd import lines as ln
from jaxdmd.prompts import Contract
from jaxdmd.proposers.offline import evaluate

__all__ = [
    "SHIFTS",
    "moves_with_reference",
    "reference_angles",
    "reference_free_line",
    "samples",
]

# the shifts of the angle reference a reference-free summand must not see (rad): not multiples
# of one another or of pi, so that no periodic term passes by coincidence
SHIFTS = (0.7, -2.3)
# a summand moves with the reference if its value moves by more than this, relative to its
# largest magnitude on the samples (a difference of angles is exact to about 1e-15)
ROUND_OFF = 1e-9
# samples each summand is evaluated on
PROBES = 257


def reference_angles(contract: Contract) -> tuple[str, ...]:
    """The angles a shift of the network's reference moves: the contract's variables in
    ``rad``, if one of them is a state (the component's own frame: a rotor angle) and one a
    boundary channel (the terminal angle it is driven at); else none."""
    variables = [*contract.states, *contract.library]
    angles = [v for v in variables if v.unit == "rad"]
    if not ({"state", "boundary"} <= {v.role for v in angles}):
        return ()
    return tuple(v.name for v in angles)


def samples(variables: Mapping[str, object], n: int = PROBES) -> dict[str, np.ndarray]:
    """``n`` samples of every variable, evenly spaced over the records (the probe points of
    :func:`reference_free_line`)."""
    out: dict[str, np.ndarray] = {}
    for name, values in variables.items():
        column = np.asarray(values, dtype=float).reshape(-1)
        rows = np.unique(np.linspace(0, column.size - 1, n).astype(int)) if column.size else []
        out[name] = column[rows]
    return out


class _Ones(ast.NodeTransformer):
    def visit_Subscript(self, node: ast.Subscript) -> ast.expr:
        if ln.param_index(node) is not None:
            return ast.Constant(1.0)
        return self.generic_visit(node)


def moves_with_reference(
    expr: ast.expr, angles: Sequence[str], data: Mapping[str, np.ndarray]
) -> bool:
    """Whether ``expr`` (its parameters set to one) changes, on ``data``, when every one of
    ``angles`` is shifted by the same constant (each of :data:`SHIFTS`). An expression that
    reads no angle, or that cannot be evaluated here (a name the data lack), does not."""
    if not {n.id for n in ast.walk(expr) if isinstance(n, ast.Name)} & set(angles):
        return False
    plain = ast.fix_missing_locations(_Ones().visit(ln.copy_tree(expr)))
    size = max((np.size(v) for v in data.values()), default=1)

    def value(values: Mapping[str, np.ndarray]) -> np.ndarray:
        return np.broadcast_to(np.asarray(evaluate(plain, values), dtype=float), (size,))

    try:
        with np.errstate(all="ignore"):
            base = value(data)
            for shift in SHIFTS:
                moved = value(dict(data) | {a: data[a] + shift for a in angles if a in data})
                both = np.isfinite(base) & np.isfinite(moved)
                if not np.any(both):
                    continue
                scale = max(float(np.max(np.abs(base[both]))), 1e-300)
                if float(np.max(np.abs(moved[both] - base[both]))) > ROUND_OFF * scale:
                    return True
    except (KeyError, ValueError, TypeError, ZeroDivisionError):
        return False
    return False


def reference_free_line(
    line: ln.Line,
    angles: Sequence[str],
    data: Mapping[str, np.ndarray],
    cache: dict[str, bool] | None = None,
) -> tuple[ln.Line, list[str]]:
    """``line`` with the summands that move with the angle reference left out (parameters
    renumbered), and those summands' text. The line as it is, with nothing left out, where no
    summand moves, where the summands share parameters, or where no summand with a parameter
    would be left. ``cache``: verdicts by summand text, shared between calls."""
    if not angles or not line.variables() & set(angles):
        return line, []
    parts = ln.summands(line.expr)
    cache = {} if cache is None else cache
    keep = []
    for part in parts:
        text = ast.unparse(part)
        if text not in cache:
            cache[text] = moves_with_reference(part, angles, data)
        keep.append(not cache[text])
    if all(keep):
        return line, []
    rest = ln.kept_summands(line, keep)
    if rest is None:
        return line, []
    return rest, [ast.unparse(p) for p, k in zip(parts, keep, strict=True) if not k]
