"""Equations as an engineer writes them (jaxdmd.pretty) and in equations.md."""

from __future__ import annotations

import ast

import pytest

from jaxdmd.pretty import equation, expression, symbol


@pytest.mark.parametrize(
    ("line", "written"),
    [
        (
            "-0.642682 * e_qp + 0.152351 * v_f + -0.00671 * i_d",
            "-0.642682 e'_q + 0.152351 v_f - 0.00671 i_d",
        ),
        ("0.974 * V * jnp.sin(delta - theta)", "0.974 V sin(δ - θ)"),
        ("376.757 * (omega - 1)", "376.757 (ω - 1)"),  # the grouping is kept
        ("a - -2.5 * b", "a + 2.5 b"),
        ("a - (b + c)", "a - (b + c)"),
        ("a + -(b + c)", "a - (b + c)"),
        ("1.5 + -x", "1.5 - x"),
        ("x * -2", "x (-2)"),
        ("-3 * e_dpp / (1 + omega)", "-3 e''_d / (1 + ω)"),
        ("0.1 * P_m ** 2 + jnp.square(omega)", "0.1 P_m² + ω²"),
        ("jnp.sqrt(V) + np.abs(theta) + math.log(V) * jnp.pi", "√V + |θ| + ln(V) π"),
        ("3.78448e-08 * delta", "3.78448·10⁻⁸ δ"),
        ("2 * 3", "2 · 3"),
    ],
)
def test_unicode_form(line, written):
    assert expression(line) == written


def test_no_jnp_and_the_same_numbers():
    line = (
        "5.44661 * e_qp + 5.38985 * (V - 1) + -8.35633 * V * jnp.cos(delta - theta) + "
        "-10.4536 * e_dpp + 7.61684 * e_qp * V * jnp.sin(delta - theta)"
    )
    for style in ("unicode", "latex"):
        text = expression(line, style)
        assert "jnp" not in text and "+ -" not in text and "*" not in text
        for number in ("5.44661", "5.38985", "8.35633", "10.4536", "7.61684"):
            assert number in text


def test_signs_folded_mean_the_same():
    """The folded form, read back with juxtaposition as multiplication, is the same number."""
    line = "-0.5 * x + -2 * y * z - -3 * x / (1 + y) + -(x - y) - 4"
    shown = expression(line)
    assert shown == "-0.5 x - 2 y z + 3 x / (1 + y) - (x - y) - 4"
    tokens = shown.split(" ")
    back = [tokens[0]]
    for t in tokens[1:]:
        if back[-1] not in ("+", "-", "/") and t not in ("+", "-", "/"):
            back.append("*")
        back.append(t)
    values = {"x": 0.7, "y": -1.3, "z": 2.1}
    assert eval(" ".join(back), {}, values) == pytest.approx(eval(line, {}, values))


def test_primes_and_greek_names():
    assert symbol("e_qp") == "e'_q" and symbol("e_dp") == "e'_d" and symbol("e_dpp") == "e''_d"
    assert symbol("delta") == "δ" and symbol("omega") == "ω" and symbol("theta") == "θ"
    assert symbol("P_e") == "P_e" and symbol("V") == "V" and symbol("i_d") == "i_d"
    assert symbol("e_qp", "latex") == "e'_{q}" and symbol("omega", "latex") == "\\omega"
    assert symbol("v_ref", "latex") == "v_{\\mathrm{ref}}"


def test_latex_form():
    rhs = "-0.642682 * e_qp + 0.152351 * v_f + -0.00671 * i_d"
    assert equation("e_qp", rhs, "latex") == (
        "\\dot{e}'_{q} = -0.642682\\, e'_{q} + 0.152351\\, v_{f} - 0.00671\\, i_{d}"
    )
    assert equation("delta", "376.757 * (omega - 1)", "latex") == (
        "\\dot{\\delta} = 376.757\\, \\left(\\omega - 1\\right)"
    )
    assert equation("P_e", "0.974 * V * jnp.sin(delta - theta)", "latex", dt=False) == (
        "P_{e} = 0.974\\, V\\, \\sin\\left(\\delta - \\theta\\right)"
    )
    assert expression("x / (1 + y)", "latex") == "\\frac{x}{1 + y}"
    assert expression("3.78448e-08 * delta", "latex") == "3.78448 \\times 10^{-8}\\, \\delta"


def test_unicode_equations():
    assert equation("delta", "376.757 * (omega - 1)") == "dδ/dt = 376.757 (ω - 1)"
    assert equation("e_qp", "-0.6 * e_qp") == "d e'_q/dt = -0.6 e'_q"
    assert equation("i_q", "0.974 * V", dt=False) == "i_q = 0.974 V"


def test_what_cannot_be_parsed_comes_back_as_it_was():
    assert expression("def (") == "def ("
    assert expression(ast.parse("x + -1", mode="eval").body) == "x - 1"


def test_equations_md_has_the_readable_latex_and_python_forms():
    from jaxdmd.prompts import Contract, Variable
    from jaxdmd.report import equation_sections
    from jaxdmd.search import Equations

    contract = Contract(
        loop="DE",
        targets=("delta", "e_qp"),
        states=(Variable("delta", "state"), Variable("e_qp", "state")),
        library=(Variable("omega", "state"), Variable("v_f", "input")),
    )
    source = (
        "def equation(delta, e_qp, omega, v_f, p):\n"
        "    return p[0] * (omega - 1), p[1] * e_qp + p[2] * v_f\n"
    )
    params = (376.757, -0.642682, 0.152351)
    de = Equations(contract=contract, source=source, params=params, losses=(0, 0), score=0.0)
    text = "\n".join(equation_sections(de))
    assert "    dδ/dt = 376.757 (ω - 1)" in text
    assert "    d e'_q/dt = -0.642682 e'_q + 0.152351 v_f" in text
    assert "\\dot{e}'_{q} &= -0.642682\\, e'_{q} + 0.152351\\, v_{f}" in text
    assert "    de_qp/dt = -0.642682 * e_qp + 0.152351 * v_f" in text  # as Python, kept
