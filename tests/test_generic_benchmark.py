"""Tests of benchmarks/generic.py's acceptance line: round-off ties, real differences do not."""

from __future__ import annotations

from benchmark_scripts import load_script

generic = load_script("generic.py", "generic_benchmark")


def _row(name: str, ours: float, theirs: float, exact: bool) -> dict:
    return {
        "system": name, "noise": 0.0,
        "jaxdmd": {"nmse_in": ours, "nmse_out": ours, "structure": exact},
        "pysindy": {"nmse_in": theirs, "nmse_out": theirs, "structure": False},
    }  # fmt: skip


def test_two_exact_models_tie_and_a_real_loss_counts():
    rows = [
        _row("exact_both", 4.5e-30, 1.4e-30, True),  # both at round-off: a tie
        _row("better", 1e-6, 1e-3, True),
        _row("worse", 3.1e-4, 2.4e-4, False),  # a real difference, above round-off
    ]
    line = generic.summary(rows)
    assert "exact structure on 2 of 3 systems (PySINDy 0)" in line
    assert "at most PySINDy's on 2 of 3" in line
    assert generic.at_most(4.5e-30, 1.4e-30) and not generic.at_most(3.1e-4, 2.4e-4)
    assert "Noise 0:" in generic.table(rows)


def test_structure_is_the_terms_not_the_signs_or_last_digits_of_their_numbers():
    """An odd function's sign comes out of it and numbers inside a function count to two
    digits, so a noisy fit of the true terms is the truth's structure; another rate is not."""
    terms = generic._sympy_terms
    truth = terms("-2 * y + 1.5 * jnp.tanh(2 * u)", ["y", "u"])
    assert terms("-2.003 * y + -1.51 * jnp.tanh(-1.981 * u)", ["y", "u"]) == truth
    assert terms("-2.003 * y + 1.51 * jnp.tanh(1.7 * u)", ["y", "u"]) != truth
    assert terms("-2 * y + 1.5 * u", ["y", "u"]) != truth
