"""Relations among the algebraic variables' measurements.

The AE loop writes each algebraic variable in the states, inputs and boundary: what the closed
model needs. But some algebraic variables are, exactly, functions of the others: a machine's
electrical power is ``v_d i_d + v_q i_q`` plus its armature losses ``r_a (i_d^2 + i_q^2)``, its
reactive power ``v_q i_d - v_d i_q``. Written in the states, such a relation passes through the
estimated states' errors and the stator lines' stand-ins; written in the measured channels, it
holds to the measurements' own accuracy (to round-off on clean channels), and it names what a
line in the states may be missing (the armature losses: a small term the closed simulation
cannot see).

:func:`measured_identities` finds them: for each algebraic variable, the best subsets of the
pairwise products of the other algebraic variables' measured values (and a constant), by
leave-one-recording-out fit as the selection holds out (:func:`jaxdmd.select.composed_lines`
builds the same products from the *lines*), the smallest within the tolerance of the best; a
relation is reported where it fits its variable on held-out recordings an order of magnitude
better than the variable's line in the states does. Nothing here knows what any variable is.
"""

from __future__ import annotations

import dataclasses
import itertools
from collections.abc import Sequence
from dataclasses import dataclass

import jax.numpy as jnp
import numpy as np

from jaxdmd import lines as ln
from jaxdmd import ties
from jaxdmd.fit import nmse
from jaxdmd.proposers.offline import subset_errors
from jaxdmd.search import (
    Equations,
    SearchState,
    cross_validated_losses,
    sample_weights,
)
from jaxdmd.select import _folds, written_as_relations
from jaxdmd.skeleton import Skeleton

__all__ = ["Identity", "fitted_nmse", "measured_identities", "nmse_text", "with_identities"]

# the most products (and a constant) in a relation: a power is four (two products and the
# armature losses' two squares)
IDENTITY_TERMS = 4
# a relation is reported where its held-out error is this many times below its variable's line
# in the states: an order of magnitude, so that two poor fits of an unrelated channel, one a
# little less poor, are not a relation
IDENTITY_MARGIN = 10.0
# the exhaustive subset search fits with a ridge of 1e-10 of the Gram matrix's trace
# (:func:`jaxdmd.proposers.offline.subset_errors`), which limits its held-out errors on exact
# data to about 1e-15: below this they are round-off, and subsets that reach it tie (the
# smallest is the relation; a constant of 1e-18 beside it is not a term)
EXACT_SUBSET = 1e-12


@dataclass(frozen=True)
class Identity:
    """An algebraic variable as a sum of products of the others' measurements.

    Attributes:
        target: the variable.
        factors: each term's pair of variables (``None``: the constant).
        coefficients: each term's coefficient, fitted on every recording.
        held_out_nmse: the relation's error on held-out recordings (NMSE, the loop's weights;
            on the fitted samples where there is one recording).
        line_nmse: the same error of the variable's line in the states (the AE equations').
    """

    target: str
    factors: tuple[tuple[str, str] | None, ...]
    coefficients: tuple[float, ...]
    held_out_nmse: float
    line_nmse: float

    def text(self, digits: int = 6) -> str:
        """The relation as an engineer writes it (``P_e = 1 i_q v_q + 0.0027 i_d^2``)."""
        from jaxdmd import pretty

        terms = []
        for factor, c in sorted(
            zip(self.factors, self.coefficients, strict=True), key=lambda t: -abs(t[1])
        ):
            value = f"{c:.{digits}g}"
            if factor is None:
                terms.append(value)
            else:
                a, b = (pretty.symbol(v) for v in factor)
                terms.append(f"{value} {a}^2" if a == b else f"{value} {a} {b}")
        body = " + ".join(terms).replace("+ -", "- ")
        return f"{pretty.symbol(self.target)} = {body}"

    def errors_text(self) -> str:
        """Both held-out errors as the log and equations.md give them (below
        :data:`EXACT_SUBSET`: round-off)."""
        return f"{nmse_text(self.held_out_nmse)}; the line {nmse_text(self.line_nmse)}"

    def as_dict(self) -> dict[str, object]:
        return {
            "terms": [None if f is None else list(f) for f in self.factors],
            "coefficients": list(self.coefficients),
            "held_out_nmse": self.held_out_nmse,
            "line_nmse": self.line_nmse,
            "text": self.text(),
        }


def nmse_text(value: float) -> str:
    """An NMSE as text: two digits, or "< 1e-12" where it is round-off (:data:`EXACT_SUBSET`)."""
    return f"{value:.2g}" if value >= EXACT_SUBSET else f"< {EXACT_SUBSET:g}"


def measured_identities(
    state: SearchState,
    equations: Equations,
    *,
    size: int = IDENTITY_TERMS,
    tolerance: float = 0.25,
) -> list[Identity]:
    """The algebraic variables of ``state`` (an AE problem: its targets are the measured
    algebraic channels) that are sums of products of the others' measurements and fit so
    :data:`IDENTITY_MARGIN` times better than their lines in ``equations`` (the AE equations
    on the same problem).

    For each variable: the pairwise products (squares included) of the other variables'
    measured values and a constant are the columns; for each number of terms up to ``size``
    the subset with the least leave-one-recording-out error (the problem's groups and sample
    weights; with one recording, the error on the fitted samples); the smallest subset within
    ``tolerance`` (relative) of the best, its coefficients fitted on every sample. It is kept if
    its error is :data:`IDENTITY_MARGIN` times below the variable's line's, scored the same way
    (:func:`jaxdmd.search.cross_validated_losses`; with one recording, the line's training
    NMSE). Empty where the problem has an operator (its targets are not the channels)."""
    problem = state.problem
    targets = list(state.contract.targets)
    if problem.operator is not None or len(targets) < 2:
        return []
    values = np.asarray(problem.targets, dtype=float)  # [targets, samples]
    groups = _folds(state)  # the recordings, as the selection holds them out
    folds = [groups == g for g in np.unique(groups)]
    held_out = len(folds) > 1
    lines, _ = ln.split_lines(equations.source)
    out = []
    for j, target in enumerate(targets):
        y = values[j]
        variance = float(np.var(y))
        others = [
            k for k in range(len(targets))
            if k != j and np.all(np.isfinite(values[k])) and np.std(values[k]) > 0
        ]  # fmt: skip
        if variance <= 0 or not np.all(np.isfinite(y)) or not others:
            continue
        pairs = list(itertools.combinations_with_replacement(others, 2))
        root = np.sqrt(sample_weights(problem, j))
        xw = np.empty((len(y), 1 + len(pairs)))  # the weighted columns, one array
        xw[:, 0] = root
        for c, (a, b) in enumerate(pairs, start=1):
            np.multiply(values[a] * values[b], root, out=xw[:, c])
        yw = y * root
        scale = len(y) * variance
        best = []
        for subsets, sse in subset_errors(xw, yw, folds, min(size, xw.shape[1])):
            i = ties.argmin(sse)
            best.append((max(float(sse[i]) / scale, 0.0), [int(c) for c in subsets[i]]))
        least = max(min(e for e, _ in best), EXACT_SUBSET)  # exact subsets tie
        error, columns = next((e, c) for e, c in best if e <= least * (1 + tolerance))
        if held_out:
            line_error = float(cross_validated_losses(state, j, [lines[j]])[0])
        else:
            line_error = float(equations.losses[j])
        if not error * IDENTITY_MARGIN < line_error:
            continue
        coefficients, *_ = np.linalg.lstsq(xw[:, columns], yw, rcond=None)
        factors = tuple(
            None if c == 0 else (targets[pairs[c - 1][0]], targets[pairs[c - 1][1]])
            for c in columns
        )
        out.append(
            Identity(
                target=target,
                factors=factors,
                coefficients=tuple(float(v) for v in coefficients),
                held_out_nmse=error,
                line_nmse=line_error,
            )
        )
    return out


def with_identities(
    equations: Equations, identities: Sequence[Identity], state: SearchState
) -> Equations | None:
    """``equations`` with each of ``identities``' variables written as its relation in the
    model's own lines: the skeleton computes the other variables' lines first and then the
    relation from their outputs by name (``P_e_ = p[12] * i_q_ * v_q_ + ...``), each term's
    coefficient a parameter set to the relation's measured coefficient. The closed model then
    computes the variable as the measurements relate it to the others (a machine's power from
    its modelled currents and voltages, armature losses included), not as a fit of the
    estimated states that passes through their errors; and whatever later changes those lines
    changes it with them. ``equations`` must have no such relation yet (one line per output).
    Each relation's line is scored on ``state``'s problem (its NMSE). None where a relation
    reads a variable that is itself written as a relation, or where the equations would not
    compile (over a skeleton's budget)."""
    contract = equations.contract
    targets = list(contract.targets)
    written = {i.target: i for i in identities}
    if any(v in written for i in identities for f in i.factors if f is not None for v in f):
        return None
    relations = {
        targets.index(identity.target): [
            (c, None if f is None else (targets.index(f[0]), targets.index(f[1])))
            for f, c in zip(identity.factors, identity.coefficients, strict=True)
        ]
        for identity in identities
    }
    compiled = written_as_relations(equations, relations)
    if compiled is None:
        return None
    skeleton, params = compiled
    fitted = _line_nmse(skeleton, params, state)
    losses = list(equations.losses)
    for identity in identities:
        j = targets.index(identity.target)
        losses[j] = fitted[j]
    return dataclasses.replace(
        equations, source=skeleton.source, params=tuple(params), losses=tuple(losses)
    )


def fitted_nmse(equations: Equations, state: SearchState) -> list[float]:
    """Each line's NMSE on ``state``'s problem with ``equations``' parameters as they are (the
    model's, after whatever refits; the problem's sample weights), in the targets' order."""
    return _line_nmse(equations.skeleton(), equations.params, state)


def _line_nmse(skeleton: Skeleton, params: Sequence[float], state: SearchState) -> list[float]:
    problem = state.problem
    data = {n: jnp.asarray(problem.variables[n]) for n in skeleton.arguments}
    predicted = np.asarray(skeleton(data, jnp.asarray(params)))
    values = np.asarray(problem.targets, dtype=float)
    return [
        float(nmse(predicted[j], values[j], sample_weights(problem, j))[0])
        for j in range(len(values))
    ]
