"""Equations as an engineer writes them: a fitted line such as
``-0.642682 * e_qp + 0.152351 * v_f + -0.00671 * i_d`` becomes
``-0.642682 e'_q + 0.152351 v_f - 0.00671 i_d`` (Unicode, for Markdown and the terminal) or
``-0.642682\\, e'_{q} + 0.152351\\, v_{f} - 0.00671\\, i_{d}`` (LaTeX).

- variable names: ``e_qp`` -> e'_q, ``e_dpp`` -> e''_d (a trailing ``p`` per prime after the d/q
  subscript), ``delta``, ``omega``, ``theta`` ... -> δ, ω, θ (``\\delta`` ...); other names stay;
- no ``jnp.``/``np.``/``math.``: ``sin(δ - θ)``, ``√x``, ``|x|``, ``ln x``, ``π``;
- signs folded: ``a + -b`` -> ``a - b``, ``a - -b`` -> ``a + b``; products are juxtaposed;
- the numbers are printed as written (the lines carry the fitted values already rounded), and
  grouping the reader needs, such as ``(ω - 1)``, is kept.

The printer walks Python's AST; it never raises: a line it cannot parse comes back as it was.
It changes only how an expression is shown, never what it computes (``model.py`` keeps the
Python lines :func:`jaxdmd.load` reads).
"""

from __future__ import annotations

import ast
import re
from collections.abc import Callable
from typing import Literal

from jaxdmd.whitelist import ALIASES, math_name

Style = Literal["unicode", "latex"]

__all__ = ["equation", "expression", "symbol"]

GREEK = [
    "alpha", "beta", "gamma", "delta", "epsilon", "zeta", "eta", "theta", "iota", "kappa",
    "lambda", "mu", "nu", "xi", "pi", "rho", "sigma", "tau", "upsilon", "phi", "chi", "psi",
    "omega",
]  # fmt: skip
_GREEK_UNICODE = dict(zip(GREEK, "αβγδεζηθικλμνξπρστυφχψω", strict=True))
_GREEK_UPPER = {"Delta": "Δ", "Theta": "Θ", "Phi": "Φ", "Psi": "Ψ", "Omega": "Ω", "Sigma": "Σ"}
_PRIMED = re.compile(r"^([A-Za-z]+)_([dq])(0?)(p{1,3})$")  # e_qp, e_dpp, x_dp, T_d0p
_SUPERSCRIPT = str.maketrans("0123456789-", "⁰¹²³⁴⁵⁶⁷⁸⁹⁻")

# precedence: the lowest binding operator of a printed piece
_SUM, _PRODUCT, _UNARY, _POWER, _ATOM = 1, 2, 3, 4, 5


def _letter(name: str, style: Style) -> str:
    if name in _GREEK_UNICODE:
        return f"\\{name}" if style == "latex" else _GREEK_UNICODE[name]
    if name in _GREEK_UPPER:
        return f"\\{name}" if style == "latex" else _GREEK_UPPER[name]
    if style == "latex" and len(name) > 1:
        return f"\\mathrm{{{name}}}"
    return name


def _parts(name: str) -> tuple[str, str, str]:
    """``name`` as (base, primes, subscript): ``e_dpp`` -> ("e", "''", "d")."""
    m = _PRIMED.match(name)
    if m:
        return m.group(1), "'" * len(m.group(4)), m.group(2) + m.group(3)
    base, _, sub = name.partition("_")
    if base and sub:
        return base, "", sub
    return name, "", ""


def symbol(name: str, style: Style = "unicode", dot: bool = False) -> str:
    """A variable's name as written: ``e_qp`` -> ``e'_q`` (``e'_{q}``), ``omega`` -> ω
    (``\\omega``). ``dot``: its time derivative, ``\\dot{e}'_{q}`` (LaTeX only)."""
    base, primes, sub = _parts(name)
    head = _letter(base, style)
    if dot and style == "latex":
        head = f"\\dot{{{head}}}"
    if not sub:
        return head + primes
    if style == "latex":
        if sub in GREEK:
            sub = _letter(sub, style)
        elif len(sub) > 1 and not sub[1:].isdigit():  # v_ref -> v_{\mathrm{ref}}, T_d0 as is
            sub = "\\mathrm{" + sub.replace("_", "\\_") + "}"
        return f"{head}{primes}_{{{sub}}}"
    return f"{head}{primes}_{_letter(sub, style)}"


def _number(value: float | int, style: Style) -> str:
    text = repr(value)
    if "e" in text and isinstance(value, float):
        mantissa, exponent = text.split("e")
        exp = str(int(exponent))
        if style == "latex":
            return f"{mantissa} \\times 10^{{{exp}}}"
        return f"{mantissa}·10{exp.translate(_SUPERSCRIPT)}"
    if text in ("inf", "nan"):
        return "\\infty" if style == "latex" and text == "inf" else ("∞" if text == "inf" else text)
    return text


class _Printer:
    def __init__(self, style: Style, names: Callable[[str], str]):
        self.style = style
        self.names = names
        self.latex = style == "latex"

    # -- signs ---------------------------------------------------------------------------------
    def negated(self, node: ast.expr) -> ast.expr | None:
        """``node`` without its leading minus sign, or None if it has none."""
        if isinstance(node, ast.Constant) and isinstance(node.value, int | float):
            if not isinstance(node.value, bool) and node.value < 0:
                return ast.Constant(-node.value)
            return None
        if isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.USub):
            return node.operand
        if isinstance(node, ast.BinOp) and isinstance(node.op, ast.Mult | ast.Div):
            left = self.negated(node.left)
            if left is not None:
                return ast.BinOp(left, node.op, node.right)
        return None

    # -- printing ------------------------------------------------------------------------------
    def wrap(self, node: ast.expr, at_least: int) -> str:
        text, prec = self.show(node)
        if prec < at_least:
            return f"\\left({text}\\right)" if self.latex else f"({text})"
        return text

    def show(self, node: ast.expr) -> tuple[str, int]:
        method = getattr(self, f"show_{type(node).__name__}", None)
        if method is None:
            return self.fallback(node), _ATOM
        return method(node)

    def fallback(self, node: ast.expr) -> str:
        text = ast.unparse(node)
        return re.sub(r"\b(?:jax\.numpy|jnp|numpy|np|math)\.", "", text)

    def show_Constant(self, node: ast.Constant) -> tuple[str, int]:
        if isinstance(node.value, bool) or not isinstance(node.value, int | float):
            return self.fallback(node), _ATOM
        if node.value < 0:
            return "-" + _number(-node.value, self.style), _UNARY
        return _number(node.value, self.style), _ATOM

    def show_Name(self, node: ast.Name) -> tuple[str, int]:
        if node.id == "pi":
            return ("\\pi" if self.latex else "π"), _ATOM
        return self.names(node.id), _ATOM

    def show_Attribute(self, node: ast.Attribute) -> tuple[str, int]:
        name = math_name(node)
        if name == "pi":
            return ("\\pi" if self.latex else "π"), _ATOM
        if name == "e":
            return "e", _ATOM
        return self.fallback(node), _ATOM

    def show_UnaryOp(self, node: ast.UnaryOp) -> tuple[str, int]:
        if isinstance(node.op, ast.UAdd):
            return self.show(node.operand)
        if isinstance(node.op, ast.USub):
            inner = self.negated(node.operand)
            if inner is not None:  # - -x
                return self.show(inner)
            return "-" + self.wrap(node.operand, _PRODUCT), _UNARY
        return self.fallback(node), _ATOM

    def show_BinOp(self, node: ast.BinOp) -> tuple[str, int]:
        op = node.op
        if isinstance(op, ast.Add | ast.Sub):
            left = self.wrap(node.left, _SUM)
            right = self.negated(node.right)
            minus = isinstance(op, ast.Sub)
            if right is not None:
                minus = not minus
            else:
                right = node.right
            # a - (b + c) keeps its parentheses; a + (b + c) does not need them
            text = self.wrap(right, _PRODUCT if minus else _SUM)
            return f"{left} {'-' if minus else '+'} {text}", _SUM
        if isinstance(op, ast.Mult):
            return self.product(node), _PRODUCT
        if isinstance(op, ast.Div):
            if self.latex:
                num = self.negated(node.left)
                sign = "-" if num is not None else ""
                num = node.left if num is None else num
                text = f"{sign}\\frac{{{self.show(num)[0]}}}{{{self.show(node.right)[0]}}}"
                return text, (_UNARY if sign else _ATOM)
            return f"{self.wrap(node.left, _PRODUCT)} / {self.wrap(node.right, _UNARY)}", _PRODUCT
        if isinstance(op, ast.Pow):
            return self.power(node.left, node.right), _POWER
        return self.fallback(node), _ATOM

    def product(self, node: ast.BinOp) -> str:
        factors: list[ast.expr] = []

        def flatten(n: ast.expr) -> None:
            if isinstance(n, ast.BinOp) and isinstance(n.op, ast.Mult):
                flatten(n.left)
                flatten(n.right)
            else:
                factors.append(n)

        flatten(node)
        out = ""
        previous_number = False
        for i, f in enumerate(factors):
            # a sign inside a product (x * -2) needs its parentheses; the leading one does not
            text = self.wrap(f, _UNARY if i == 0 else _POWER)
            number = isinstance(f, ast.Constant)
            if i == 0:
                out = text
            elif number or (previous_number and text[:1].isdigit()):
                out += " \\cdot " if self.latex else " · "
                out += text
            else:
                out += "\\, " if self.latex else " "
                out += text
            previous_number = number
        return out

    def power(self, base: ast.expr, exponent: ast.expr) -> str:
        b = self.wrap(base, _ATOM)
        if isinstance(exponent, ast.Constant) and isinstance(exponent.value, int | float):
            value = exponent.value
            if float(value).is_integer() and not isinstance(value, bool):
                n = str(int(value))
                if self.latex:
                    return f"{b}^{{{n}}}"
                return b + n.translate(_SUPERSCRIPT)
        e = self.show(exponent)[0]
        return f"{b}^{{{e}}}" if self.latex else f"{b}^({e})"

    def show_Call(self, node: ast.Call) -> tuple[str, int]:
        name = math_name(node.func)
        if name is None and isinstance(node.func, ast.Name):
            name = node.func.id
        name = ALIASES.get(name or "", name)
        if name is None or node.keywords:
            return self.fallback(node), _ATOM
        args = [self.show(a)[0] for a in node.args]
        latex = self.latex
        if len(args) == 1:
            (x,) = args
            if name == "sqrt":
                if latex:
                    return f"\\sqrt{{{x}}}", _ATOM
                return f"√{self.wrap(node.args[0], _ATOM)}", _ATOM
            if name == "abs":
                return (f"\\left|{x}\\right|" if latex else f"|{x}|"), _ATOM
            if name == "square":
                return self.power(node.args[0], ast.Constant(2)), _POWER
            if name == "exp" and latex:
                return f"e^{{{x}}}", _POWER
            known = {"log": "ln", "sign": "sgn"}.get(name, name)
            if name in ("sin", "cos", "tan", "exp", "log", "tanh", "sinh", "cosh", "arctan",
                        "arcsin", "arccos", "sign"):  # fmt: skip
                if latex:
                    op = f"\\{known}" if known != "sgn" else "\\operatorname{sgn}"
                    return f"{op}\\left({x}\\right)", _ATOM
                return f"{known}({x})", _ATOM
        if name in ("maximum", "minimum", "arctan2", "where", "clip"):
            label = {"maximum": "max", "minimum": "min", "arctan2": "atan2"}.get(name, name)
            joined = ", ".join(args)
            if latex:
                op = {"max": "\\max", "min": "\\min"}.get(label, f"\\operatorname{{{label}}}")
                return f"{op}\\left({joined}\\right)", _ATOM
            return f"{label}({joined})", _ATOM
        return self.fallback(node), _ATOM

    def show_Compare(self, node: ast.Compare) -> tuple[str, int]:
        ops = {ast.Lt: "<", ast.Gt: ">", ast.LtE: "≤", ast.GtE: "≥", ast.Eq: "=", ast.NotEq: "≠"}
        latex_ops = {"≤": "\\le", "≥": "\\ge", "≠": "\\ne"}
        parts = [self.wrap(node.left, _SUM)]
        for op, right in zip(node.ops, node.comparators, strict=True):
            sym = ops.get(type(op))
            if sym is None:
                return self.fallback(node), _ATOM
            parts += [latex_ops.get(sym, sym) if self.latex else sym, self.wrap(right, _SUM)]
        return " ".join(parts), 0


def _source(expr: str | ast.expr) -> ast.expr | None:
    if isinstance(expr, ast.expr):
        return expr
    try:
        return ast.parse(expr.strip(), mode="eval").body
    except SyntaxError:
        return None


def expression(expr: str | ast.expr, style: Style = "unicode") -> str:
    """A Python expression (a fitted line's right-hand side) as an engineer writes it.

    >>> expression("-0.642682 * e_qp + 0.152351 * v_f + -0.00671 * i_d")
    "-0.642682 e'_q + 0.152351 v_f - 0.00671 i_d"
    >>> expression("0.974 * V * jnp.sin(delta - theta)")
    '0.974 V sin(δ - θ)'
    """
    node = _source(expr)
    if node is None:
        return expr if isinstance(expr, str) else ast.unparse(expr)
    try:
        return _Printer(style, lambda n: symbol(n, style)).show(node)[0]
    except (RecursionError, ValueError, TypeError, AttributeError):
        return expr if isinstance(expr, str) else ast.unparse(expr)


def equation(target: str, expr: str | ast.expr, style: Style = "unicode", dt: bool = True) -> str:
    """``target``'s equation: ``dδ/dt = 376.757 (ω - 1)``, ``d e'_q/dt = ...`` (``dt``: a
    state equation) or
    ``i_q = ...``; LaTeX: ``\\dot{\\delta} = 376.757\\, \\left(\\omega - 1\\right)``."""
    rhs = expression(expr, style)
    if style == "latex":
        return f"{symbol(target, style, dot=dt)} = {rhs}"
    lhs = symbol(target)
    if dt:  # dδ/dt, d e'_q/dt (a space where "de'_q" could read as one name)
        lhs = f"d{lhs}/dt" if len(lhs) == 1 else f"d {lhs}/dt"
    return f"{lhs} = {rhs}"
