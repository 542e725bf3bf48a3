"""Choices on errors that agree to nine significant digits are ties (jaxdmd.ties)."""

from __future__ import annotations

import numpy as np

from jaxdmd import ties


def test_values_equal_to_nine_digits_are_ties_and_real_differences_rank():
    x = 0.0123456789012
    assert ties.settled(x) == ties.settled(x * (1 + 1e-13)) == ties.settled(x * (1 - 1e-13))
    assert ties.settled(x) != ties.settled(x * (1 + 1e-6))
    assert ties.settled(0.0) == 0.0 and ties.settled(-np.inf) == -np.inf
    assert np.isnan(ties.settled(np.nan))
    # the first of the tied values wins, whichever carries the rounding
    assert ties.argmin([x * (1 + 1e-14), x, 2 * x]) == 0
    assert ties.argmin([x, x * (1 - 1e-14), 2 * x]) == 0
    assert ties.argmin([x, x * (1 - 1e-6), 2 * x]) == 1
    assert ties.argmax([x, x * (1 + 1e-14)]) == 0
    assert ties.settled_array(np.full((2, 3), x)).shape == (2, 3)
