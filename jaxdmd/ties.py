"""Choices that the last bits of the arithmetic must not make.

The search ranks candidates by floating-point errors, and many of its choices are between
candidates that are equally good *in exact arithmetic*: two islands holding the same seed, a term
``omega`` against ``(omega - 1)`` next to a constant, one line written in two orders. Computed,
such ties differ in the last bits, and which side wins then depends on the BLAS thread count, the
jax release or the machine; one flipped choice sends the whole search down another path (measured:
the same Table I pair, the same data to 1e-13, searched on two machines, reset different islands
at round 4 and ended with other equations).

Every discrete choice on an error therefore compares errors rounded to :data:`SIGNIFICANT`
significant digits: values that agree that far are a tie, and the tie is broken by what the
caller puts next (shorter, older, first in a fixed order), never by rounding noise. Nine digits
keep any real difference (the search's errors differ by far more when candidates differ) and
absorb the ~1e-13 relative noise of reordered sums.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

SIGNIFICANT = 9


def settled(value: float) -> float:
    """``value`` rounded to :data:`SIGNIFICANT` significant digits (infinities and NaN kept)."""
    value = float(value)
    if value == 0.0 or not np.isfinite(value):
        return value
    return float(f"{value:.{SIGNIFICANT}g}")


def settled_array(values: Sequence[float] | np.ndarray) -> np.ndarray:
    """:func:`settled` of every element."""
    arr = np.asarray(values, dtype=np.float64)
    return np.array([settled(v) for v in arr.ravel()], dtype=np.float64).reshape(arr.shape)


def argmin(values: Sequence[float] | np.ndarray) -> int:
    """The first index of the least value, values equal to :data:`SIGNIFICANT` digits tied."""
    return int(np.argmin(settled_array(values)))


def argmax(values: Sequence[float] | np.ndarray) -> int:
    """The first index of the largest value, values equal to :data:`SIGNIFICANT` digits tied."""
    return int(np.argmax(settled_array(values)))
