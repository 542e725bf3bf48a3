"""Physical parameters of a discovered generator model, with standard errors (issue #18, item 1).

A discovered model is a set of fitted lines. This module expands each line into monomials of the
measured variables (``p[0] * (omega - 1)`` gives ``omega`` and ``1``; ``V * sin(delta - theta)``
is read as ``v_d``, ``V * cos(delta - theta)`` as ``v_q``), compares each equation's monomial set
with the forms of the machine-model families, and maps the coefficients to physical parameters.

Families (states; the stator reactances X_d, X_q of
``0 = v_q + r_a i_q - e_q + X_d i_d``, ``0 = v_d + r_a i_d - e_d - X_q i_q``):

- ``classical``: delta, omega; e_q = E' constant, e_d = 0, X_d = X_q = x'_d;
- ``one-axis``: adds e'_q; e_d = 0, X_d = x'_d, X_q = x_q;
- ``two-axis``: adds e'_d; e_d = e'_d, X_d = x'_d, X_q = x'_q;
- ``psat-5.1`` (PSAT type I, sub-transient): adds e''_d; e_d = e''_d, X_d = X_q = x'_d (PSAT 5.1
  uses x'_d where other models use x''_q, ``reference/psat-syn-5.1.md``); an ``e_qpp`` equation
  (e''_q), where the model has one, is mapped the same way as e''_d.

The state equations and what their coefficients identify (c_u: the fitted coefficient of u):

- ``d delta/dt = Omega_b (omega - 1)``: Omega_b = c_omega (and -c_1, a second estimate);
- ``M d omega/dt = P_m - P_e - D (omega - 1)``: only 1/M and D/M are identifiable; M = -1/c_P_e
  and, when the P_m term is there, a second estimate M = 1/c_P_m (both are reported; they differ
  when the fit does not hold the PSAT form exactly). H = M/2 in seconds on the base the data are
  in per unit (the benchmark's: the 100 MVA system base, not the machine rating). D = -c_omega M
  (from M = -1/c_P_e); without an omega term D is reported as 0, 'not in the model'. A constant
  term is mapped only as the second Omega_b estimate (delta); in the omega equation it mixes
  P_m/M and D/M and is reported unmapped.
- first-order lags ``T dx/dt = -x + sum_u g_u u``: T = -1/c_x, g_u = c_u T. This gives T'_d0 and
  x_d - x'_d (e'_q: the i_d gain is -(x_d - x'_d); 1/c_v_f is a second estimate of T'_d0),
  T'_q0 and x_q - x'_q - gamma_q (e'_d; gamma_q = 0 outside PSAT 5.1), T''_q0 and
  x'_q - x'_d + gamma_q (e''_d; 1/c_e_dp is a second estimate of T''_q0). With
  gamma_q = (x'_d/x'_q)(T''_q0/T'_q0)(x_q - x'_q), the sum of the two gains is x_q - x'_d; with
  x'_d from the stator lines x_q and x'_q (the larger root of
  x'_q^2 - x'_q (x_q - a + c) + c x_q = 0, a the e'_d gain, c = x'_d T''_q0/T'_q0) follow.

A constant term in d e'_d/dt, d e''_d/dt or d e''_q/dt (no family has one there) is set aside,
and the equation counted as matching, when it is within ``SET_ASIDE_STDERRS`` (2) standard
errors of zero; it is reported as ``constant term (set aside)``. Without standard errors it
stays a term no family has.

The stator lines, solved for the currents (det = r_a^2 + X_d X_q):

    i_d = [r_a (e_d - v_d) + X_q (e_q - v_q)] / det
    i_q = [r_a (e_q - v_q) - X_d (e_d - v_d)] / det

each coefficient pair (state, voltage) gives one combination (their mean is used): r_a/det,
X_q/det from i_d, r_a/det, X_d/det from i_q. With both lines, det = 1/(a^2 + b c) and r_a, X_d,
X_q all follow; with one line, X_d = X_q is assumed (PSAT 5.1, classical). The P_e line is
reported but not used.

Standard errors (nothing is refitted): at each line's fitted parameters the Jacobian J of its
(operator-smoothed, weighted) predictions on the loop's data and the residuals r give the
line's covariance. Different lines are taken as independent (block-diagonal covariance) and the
physical parameters get their errors by the delta method (jax gradients of the maps). Where the
equations' parameters were refitted on other data than the problem given (an integral-form
refit, the refit by simulation), the residuals are those of the given problem at those
parameters.

The rows' errors are correlated wherever the operator's windows share samples (the integral
form's overlapping windows, the matched smoothing's band; rows of different recordings never),
so each line's covariance is the sandwich ``N/(N-P) B (sum_{i,j} g_i g_j^T) B``,
``B = (J^T W J)^-1``, ``g_i = w_i r_i J_i``, over the pairs of rows whose windows overlap (a
heteroskedasticity-and-autocorrelation-consistent estimate with a uniform kernel as wide as the
windows: white noise on the samples makes the residuals correlated over exactly that span).
``correlated=False`` gives the textbook ``s^2 (J^T W J)^-1``, ``s^2 = sum(w r^2) / (N - P)``,
which takes the rows as independent and is too small on such fits:
Measured over thirty noise draws (0.5 % of each state's range; three 10 s recordings, 0.01 s
samples) of the classical machine with damping, refitted in the integral form (3 s windows):
the estimates of Omega_b, H and D scattered 3.5-5.9x more than the plain ``s^2 (J^T W J)^-1``
errors (13-47 % of them within two errors of the truth), 1.2-1.3x more than these (83-93 %);
with matched derivatives 1.2-5.3x and 0.8-1.1x (87-93 %). These are still somewhat low when a
recording holds few windows (the residuals are fitted ones), and one draw's error is itself
uncertain by about +-40 %.
"""

from __future__ import annotations

import ast
import math
from collections import Counter
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxdmd import lines as ln
from jaxdmd.search import Equations, Problem, compiled_lines, sample_weights

__all__ = [
    "SET_ASIDE_STDERRS",
    "Coefficient",
    "EquationMatch",
    "NonLinearInParameters",
    "PhysicalParameter",
    "PhysicalReport",
    "discovery_section",
    "expand",
    "line_covariance",
    "physical_parameters",
    "section",
    "with_section",
]


class NonLinearInParameters(ValueError):
    """A summand holds a parameter inside a function (``sin(p[0] * delta)``)."""


# ----------------------------------------------------------------------------------------------
# lines as polynomials in the variables, with coefficients polynomial in the parameters

_Term = tuple[float, tuple[tuple[int, int], ...], tuple[tuple[str, int], ...]]  # c, params, atoms

_MODULES = ("jnp", "np", "math", "numpy", "jax")


def _has_param(node: ast.AST) -> bool:
    return bool(ln.param_indices(node))


class _Canon(ast.NodeTransformer):
    """``jnp.sin`` -> ``sin``, ``1.0`` -> ``1``."""

    def visit_Attribute(self, node: ast.Attribute) -> ast.AST:
        base = node.value
        while isinstance(base, ast.Attribute):
            base = base.value
        if isinstance(base, ast.Name) and base.id in _MODULES and node.attr != "pi":
            return ast.Name(node.attr, ast.Load())
        return self.generic_visit(node)

    def visit_Constant(self, node: ast.Constant) -> ast.AST:
        if isinstance(node.value, float) and node.value.is_integer():
            return ast.Constant(int(node.value))
        return node


def _atom(node: ast.expr) -> str:
    return ast.unparse(ast.fix_missing_locations(_Canon().visit(ln.copy_tree(node))))


def _mul(a: list[_Term], b: list[_Term]) -> list[_Term]:
    out = []
    for ca, pa, xa in a:
        for cb, pb, xb in b:
            p = Counter(dict(pa)) + Counter()
            for k, n in pb:
                p[k] = p.get(k, 0) + n
            x = Counter(dict(xa))
            for k, n in xb:
                x[k] = x.get(k, 0) + n
            out.append(
                (
                    ca * cb,
                    tuple(sorted((k, n) for k, n in p.items() if n)),
                    tuple(sorted((k, n) for k, n in x.items() if n)),
                )
            )
    return out


def _expand(node: ast.expr) -> list[_Term]:
    if isinstance(node, ast.Constant) and isinstance(node.value, int | float):
        return [(float(node.value), (), ())]
    k = ln.param_index(node)
    if k is not None:
        return [(1.0, ((k, 1),), ())]
    if isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.USub | ast.UAdd):
        s = -1.0 if isinstance(node.op, ast.USub) else 1.0
        return [(s * c, p, x) for c, p, x in _expand(node.operand)]
    if isinstance(node, ast.BinOp):
        if isinstance(node.op, ast.Add | ast.Sub):
            s = -1.0 if isinstance(node.op, ast.Sub) else 1.0
            return _expand(node.left) + [(s * c, p, x) for c, p, x in _expand(node.right)]
        if isinstance(node.op, ast.Mult):
            return _mul(_expand(node.left), _expand(node.right))
        if isinstance(node.op, ast.Div):
            right = _expand(node.right)
            if len(right) == 1 and right[0][0] != 0:
                c, p, x = right[0]
                inv = (1.0 / c, tuple((k, -n) for k, n in p), tuple((a, -n) for a, n in x))
                return _mul(_expand(node.left), [inv])
        if (
            isinstance(node.op, ast.Pow)
            and isinstance(node.right, ast.Constant)
            and isinstance(node.right.value, int | float)
            and float(node.right.value).is_integer()
            and 1 <= node.right.value <= 4
        ):
            out = [(1.0, (), ())]
            for _ in range(int(node.right.value)):
                out = _mul(out, _expand(node.left))
            return out
    if _has_param(node):
        raise NonLinearInParameters(ast.unparse(node))
    return [(1.0, (), ((_atom(node), 1),))]


_ALIASES = (("v_d", "sin(delta - theta)"), ("v_q", "cos(delta - theta)"))


def _monomial(atoms: tuple[tuple[str, int], ...]) -> str:
    x = dict(atoms)
    for alias, trig in _ALIASES:
        while x.get("V", 0) >= 1 and x.get(trig, 0) >= 1:
            x["V"] -= 1
            x[trig] -= 1
            x[alias] = x.get(alias, 0) + 1
    parts = [a if n == 1 else f"{a}**{n}" for a, n in sorted(x.items()) if n]
    return " * ".join(parts) if parts else "1"


@dataclass(frozen=True)
class Coefficient:
    """The coefficient of one monomial of a line: a polynomial in the line's parameters."""

    terms: tuple[tuple[float, tuple[tuple[int, int], ...]], ...]
    offset: int = 0  # where the line's parameters start in the stacked vector

    def __call__(self, theta: jax.Array) -> jax.Array:
        total = jnp.asarray(0.0)
        for c, params in self.terms:
            v = jnp.asarray(c)
            for k, n in params:
                v = v * theta[self.offset + k] ** n
            total = total + v
        return total


def expand(line: ln.Line, offset: int = 0) -> dict[str, Coefficient]:
    """``line`` as ``{monomial: coefficient}`` (``p[0] * (omega - 1)`` gives ``omega: p[0]``
    and ``1: -p[0]``); raises :class:`NonLinearInParameters` for a parameter inside a
    function."""
    grouped: dict[str, list] = {}
    for c, p, x in _expand(line.expr):
        grouped.setdefault(_monomial(x), []).append((c, p))
    return {m: Coefficient(tuple(t), offset) for m, t in grouped.items()}


# ----------------------------------------------------------------------------------------------
# standard errors of a line's parameters


def line_covariance(
    skeleton: Any,
    params: Sequence[float],
    variables: Mapping[str, Any],
    target: Any,
    weights: Any = None,
    operator: Any = None,
    *,
    correlated: bool = True,
) -> np.ndarray:
    """The parameter covariance of a one-output skeleton at ``params`` on the given data.

    ``J`` is the Jacobian (``jax.jacfwd``) of the predictions (after ``operator``, as the fit
    compares them) with respect to the parameters, ``W`` the sample weights,
    ``s^2 = sum(w r^2) / (N_w - P)`` with ``N_w`` the number of samples of positive weight.
    A singular ``J^T W J`` gives ``inf`` variances where the parameter is not determined.
    With ``correlated`` (the default) the sandwich over the rows whose ``operator`` windows
    overlap (module docstring; without an operator, rows are independent but may differ in
    variance); without it ``s^2 (J^T W J)^-1``.
    """
    p = jnp.asarray(np.asarray(params, dtype=float))
    y = jnp.asarray(np.asarray(target, dtype=float)).reshape(-1)
    w = jnp.ones_like(y) if weights is None else jnp.asarray(np.asarray(weights, dtype=float))
    data = {a: variables[a] for a in skeleton.arguments}

    def predict(q, data):
        pred = skeleton(data, q)[:1]
        pred = jnp.broadcast_to(pred, (1, y.shape[0]))
        return (pred if operator is None else operator(pred))[0]

    # one compiled program for the predictions and their Jacobian (op by op, every line's
    # operations compiled one at a time: ten seconds for the benchmark's eleven lines)
    pred, jac = jax.jit(lambda q, data: (predict(q, data), jax.jacfwd(predict)(q, data)))(p, data)
    r = pred - y  # jac: [N, P]
    n_eff = int(np.sum(np.asarray(w) > 0))
    dof = max(1, n_eff - p.shape[0])
    s2 = float(jnp.sum(w * r * r)) / dof
    jtj = np.asarray(jac.T @ (w[:, None] * jac), dtype=float)
    if not np.all(np.isfinite(jtj)):
        return np.full((p.shape[0], p.shape[0]), np.inf)
    singular = False
    try:
        bread = np.linalg.inv(jtj)
    except np.linalg.LinAlgError:
        bread, singular = np.linalg.pinv(jtj), True
    if correlated:
        g = np.asarray(w * r, dtype=float)[:, None] * np.asarray(jac, dtype=float)
        cov = bread @ _overlap_sum(g, operator) @ bread * (n_eff / dof)
    else:
        cov = bread * s2
    if singular:
        cov[np.diag(jtj) <= 0] = np.inf
    return cov


def _overlap_sum(g: np.ndarray, operator: Any) -> np.ndarray:
    """``sum g_i g_j^T`` over the pairs of rows whose ``operator`` windows share samples
    (``|i - j| <= L``, both in one run of overlapping windows: one recording), made positive
    semi-definite. Without an operator, ``sum g_i g_i^T``."""
    n = g.shape[0]
    if operator is None:
        return g.T @ g
    index = np.asarray(operator.index)
    lo, hi = index.min(axis=1), index.max(axis=1)
    span = int(np.max(hi - lo))  # rows further apart than this share no sample
    run = np.concatenate([[0], np.cumsum(hi[:-1] < lo[1:])])  # a new run where windows part
    first = np.searchsorted(run, run, side="left")
    last = np.searchsorted(run, run, side="right") - 1
    rows = np.arange(n)
    upper = np.minimum(rows + span, last)
    lower = np.maximum(rows - span, first)
    cumulative = np.concatenate([np.zeros((1, g.shape[1])), np.cumsum(g, axis=0)])
    near = cumulative[upper + 1] - cumulative[lower]  # sum of g_j over the overlapping rows
    total = g.T @ near
    total = (total + total.T) / 2
    values, vectors = np.linalg.eigh(total)
    return (vectors * np.maximum(values, 0.0)) @ vectors.T


def _line_covariances(
    eqs: Equations, problem: Problem, correlated: bool = True
) -> list[np.ndarray | None]:
    """Each line's parameter covariance on ``problem`` (None where it cannot be computed)."""
    lines, mappings = ln.split_lines(eqs.source)
    compiled = dict(compiled_lines(eqs.contract, lines))
    out: list[np.ndarray | None] = []
    for j, (target, mapping) in enumerate(zip(eqs.contract.targets, mappings, strict=True)):
        sk = compiled.get(j)
        if sk is None or target not in problem.target_names or not mapping:
            out.append(None)
            continue
        row = problem.target_names.index(target)
        params = [eqs.params[i] for i in mapping]
        try:
            out.append(
                line_covariance(
                    sk,
                    params,
                    problem.variables,
                    problem.targets[row],
                    sample_weights(problem, row),
                    problem.operator,
                    correlated=correlated,
                )
            )
        except (KeyError, ValueError):
            out.append(None)
    return out


# ----------------------------------------------------------------------------------------------
# matching


@dataclass(frozen=True)
class PhysicalParameter:
    """One physical parameter: value, standard error (None: no data given or not in the model),
    unit, the equation it comes from, and a note."""

    name: str
    value: float
    stderr: float | None
    unit: str
    source: str
    note: str = ""

    def value_text(self) -> str:
        """The value as the reports print it."""
        return f"{self.value:.6g}" if math.isfinite(self.value) else str(self.value)

    def stderr_text(self) -> str:
        """The standard error as the reports print it (empty when there is none)."""
        return "" if self.stderr is None else f"{self.stderr:.3g}"

    def text(self) -> str:
        """``value ± stderr``, or the value alone when there is no standard error."""
        se = self.stderr_text()
        return f"{self.value_text()} ± {se}" if se else self.value_text()

    def to_dict(self) -> dict[str, Any]:
        def num(x):
            return None if x is None or not math.isfinite(x) else float(x)

        return {
            "name": self.name,
            "value": num(self.value),
            "stderr": num(self.stderr),
            "unit": self.unit,
            "source": self.source,
            "note": self.note,
        }


@dataclass(frozen=True)
class EquationMatch:
    """How one equation compares with the families' form: its monomials, the expected ones
    it holds, the ones no family expects there (``unmatched``)."""

    equation: str
    terms: tuple[str, ...]
    matched: bool
    unmatched: tuple[str, ...] = ()
    missing: tuple[str, ...] = ()
    note: str = ""

    def to_dict(self) -> dict[str, Any]:
        return {
            "equation": self.equation,
            "terms": list(self.terms),
            "matched": self.matched,
            "unmatched": list(self.unmatched),
            "missing": list(self.missing),
            "note": self.note,
        }


@dataclass(frozen=True)
class PhysicalReport:
    """The family the model matches (None: none), the parameters and every equation's match."""

    family: str | None
    parameters: tuple[PhysicalParameter, ...]
    equations: tuple[EquationMatch, ...]
    notes: tuple[str, ...] = ()

    def get(self, name: str) -> PhysicalParameter | None:
        return next((p for p in self.parameters if p.name == name), None)

    def to_dict(self) -> dict[str, Any]:
        return {
            "family": self.family,
            "parameters": [p.to_dict() for p in self.parameters],
            "equations": [e.to_dict() for e in self.equations],
            "notes": list(self.notes),
        }

    def markdown(self) -> str:
        head = "## Physical parameters"
        if self.family is None:
            out = [head, "", "No machine-model family matches the discovered equations."]
        else:
            out = [head, "", f"Family: **{self.family}**."]
        if self.parameters:
            out += ["", "| parameter | value | std. error | unit | from | note |"]
            out += ["|---|---|---|---|---|---|"]
            for p in self.parameters:
                val, se = p.value_text(), p.stderr_text()
                out.append(f"| {p.name} | {val} | {se} | {p.unit} | {p.source} | {p.note} |")
        bad = [e for e in self.equations if not e.matched]
        if bad:
            out += ["", "Equations that do not match a family's form:", ""]
            for e in bad:
                extra = ", ".join(f"`{t}`" for t in e.unmatched) or "none"
                miss = ", ".join(f"`{t}`" for t in e.missing) or "none"
                out.append(
                    f"- {e.equation}: terms no family has: {extra}; missing: {miss}"
                    + (f" ({e.note})" if e.note else "")
                )
        out += ["", *self.notes] if self.notes else []
        return "\n".join(out) + "\n"


SET_ASIDE_STDERRS = 2.0
"""A constant term in a state equation whose family form has none (d e'_d/dt, d e''_d/dt,
d e''_q/dt) is set aside, and the equation matched, when ``|c| <= SET_ASIDE_STDERRS * se(c)``:
the fit does not tell it from zero (a two-sided test at about 5 %). It is reported as
``constant term (set aside)``. Without standard errors (no problems given) it is never set
aside."""

_FAMILIES = (
    ("classical", ("delta", "omega")),
    ("one-axis", ("delta", "omega", "e_qp")),
    ("two-axis", ("delta", "omega", "e_qp", "e_dp")),
    ("psat-5.1", ("delta", "omega", "e_qp", "e_dp", "e_dpp")),
)

# state equation forms: required monomials, optional monomials
_DE_FORMS: dict[str, tuple[frozenset[str], frozenset[str]]] = {
    "delta": (frozenset({"omega"}), frozenset({"1"})),
    "omega": (frozenset({"P_e"}), frozenset({"P_m", "omega", "1"})),
    "e_qp": (frozenset({"e_qp", "i_d"}), frozenset({"v_f", "1"})),
    "e_dp": (frozenset({"e_dp", "i_q"}), frozenset()),
    "e_dpp": (frozenset({"e_dpp", "e_dp", "i_q"}), frozenset()),
    "e_qpp": (frozenset({"e_qpp", "e_qp", "i_d"}), frozenset()),
}
# d e'_q/dt with the stator equation v_q = e'_q - x'_d i_d substituted for i_d (r_a i_q
# neglected): (-(x_d / x'_d) e'_q + ((x_d - x'_d) / x'_d) v_q + v_f) / T'_d0. With both v_q and
# i_d measured the data cannot tell the two forms apart; this one identifies T'_d0 and x_d / x'_d.
_E_QP_TERMINAL = (frozenset({"e_qp", "v_q", "v_f"}), frozenset({"1"}))


def _check(name: str, coefs: Mapping[str, Any], required, optional, note="") -> EquationMatch:
    terms = tuple(sorted(coefs))
    unmatched = tuple(t for t in terms if t not in required | optional)
    missing = tuple(sorted(required - set(coefs)))
    return EquationMatch(name, terms, not unmatched and not missing, unmatched, missing, note)


def _split(eqs: Equations, offset: int) -> tuple[list[dict | None], list[str], int]:
    """Each line's monomials (None where a parameter sits inside a function), the notes."""
    lines, _ = ln.split_lines(eqs.source)
    out, notes = [], []
    for line in lines:
        try:
            out.append(expand(line, offset))
        except NonLinearInParameters as err:
            out.append(None)
            notes.append(str(err))
        offset += line.n_params
    return out, notes, offset


def physical_parameters(
    de: Equations,
    ae: Equations | None = None,
    de_problem: Problem | None = None,
    ae_problem: Problem | None = None,
    *,
    correlated: bool = True,
) -> PhysicalReport:
    """Match the discovered equations with the machine-model families and map their
    coefficients to physical parameters (module docstring). The problems, when given, are the
    loops' data, for standard errors; without them every ``stderr`` is None. ``correlated``
    (default): errors correlated over the problems' operator windows (`line_covariance`)."""
    de_lines, de_notes, n_de = _split(de, 0)
    ae_lines, ae_notes, n_all = _split(ae, n_de) if ae is not None else ([], [], n_de)
    # stacked parameters and block-diagonal covariance (NaN where no data: stderr None)
    theta = np.zeros(n_all)
    cov = np.zeros((n_all, n_all))
    known = np.zeros(n_all, dtype=bool)
    for eqs, problem, start in ((de, de_problem, 0), (ae, ae_problem, n_de)):
        if eqs is None:
            continue
        lines, mappings = ln.split_lines(eqs.source)
        covs = (
            _line_covariances(eqs, problem, correlated)
            if problem is not None
            else [None] * len(lines)
        )
        off = start
        for line, mapping, c in zip(lines, mappings, covs, strict=True):
            end = off + line.n_params
            theta[off:end] = [eqs.params[i] for i in mapping]
            if c is not None and c.shape == (line.n_params, line.n_params):
                cov[off:end, off:end] = c
                known[off:end] = True
            off = end
    theta_j = jnp.asarray(theta)

    params: list[PhysicalParameter | None] = []
    pending: list[tuple[int, str, Callable, str, str, str]] = []  # what add() has to evaluate

    def stderr(grad: np.ndarray) -> float | None:
        """The delta method's standard error of a function of theta with gradient ``grad``."""
        used = grad != 0
        if not used.any():
            return 0.0
        if not known[used].all():
            return None
        sub = cov[np.ix_(used, used)]
        se = float(np.sqrt(max(grad[used] @ sub @ grad[used], 0.0)))
        return se if math.isfinite(se) else None

    def value_and_stderr(fn: Callable) -> tuple[float, float | None]:
        grad = np.asarray(jax.grad(lambda t: fn(t))(theta_j))
        return float(fn(theta_j)), stderr(grad)

    def add(name, fn: Callable, unit, source, note=""):
        # evaluated with every other one at the end, in one compiled program: op by op, each
        # parameter's gradient compiled its own indexing operations (seconds in all)
        pending.append((len(params), name, fn, unit, source, note))
        params.append(None)

    matches: list[EquationMatch] = []
    set_aside: list[str] = []
    targets = de.contract.targets
    eq = {t: c for t, c in zip(targets, de_lines, strict=True)}
    ok: dict[str, bool] = {}
    for t in targets:
        src = f"d{t}/dt"
        if t not in _DE_FORMS:
            matches.append(EquationMatch(src, (), False, note="no family has this state"))
            ok[t] = False
            continue
        if eq[t] is None:
            matches.append(EquationMatch(src, (), False, note="a parameter inside a function"))
            ok[t] = False
            continue
        m = _check(src, eq[t], *_DE_FORMS[t])
        if t == "e_qp" and not m.matched:
            terminal = _check(
                src, eq[t], *_E_QP_TERMINAL,
                note="the terminal-voltage form: v_q = e'_q - x'_d i_d substituted for i_d",
            )  # fmt: skip
            m = terminal if terminal.matched else m
        if not m.matched and m.unmatched == ("1",) and not m.missing:
            # a constant no family has there: set aside when zero is within its error
            value, se = value_and_stderr(eq[t]["1"])
            if se is not None and abs(value) <= SET_ASIDE_STDERRS * se:
                why = (
                    f"constant term {value:.3g} ± {se:.2g} set aside: within "
                    f"{SET_ASIDE_STDERRS:g} standard errors of zero"
                )
                m = EquationMatch(src, m.terms, True, (), (), why)
                params.append(
                    PhysicalParameter(
                        "constant term (set aside)", value, se, "1/s", src, why.split(": ")[1]
                    )
                )
                set_aside.append(f"{src}: {why}")
        matches.append(m)
        ok[t] = m.matched

    family = None
    for name, states in _FAMILIES:
        if all(ok.get(s) for s in states) and all(s in states for s in targets if s != "e_qpp"):
            family = name
    partial = family is None
    if family is None:
        # the largest family whose states are all there and match, ignoring extra equations
        for name, states in _FAMILIES:
            if all(ok.get(s) for s in states):
                family = name
    psat = family == "psat-5.1"

    if ok.get("delta"):
        c = eq["delta"]
        add("Omega_b", c["omega"], "rad/s", "ddelta/dt", "coefficient of omega")
        if "1" in c:
            add(
                "Omega_b (constant term)",
                lambda t, c=c: -c["1"](t),
                "rad/s",
                "ddelta/dt",
                "second estimate: minus the constant term",
            )
    if ok.get("omega"):
        c = eq["omega"]
        m_pe = lambda t, c=c: -1.0 / c["P_e"](t)  # noqa: E731
        add("M", m_pe, "s", "domega/dt", "M = 2H = -1/c(P_e), on the data's per-unit base")
        add("H", lambda t: m_pe(t) / 2, "s", "domega/dt", "H = M/2, on the data's per-unit base")
        if "P_m" in c:
            add(
                "M (from P_m)",
                lambda t, c=c: 1.0 / c["P_m"](t),
                "s",
                "domega/dt",
                "second estimate: 1/c(P_m)",
            )
        if "omega" in c:
            add("D", lambda t, c=c: -c["omega"](t) * m_pe(t), "pu", "domega/dt", "D = -c(omega) M")
        else:
            params.append(PhysicalParameter("D", 0.0, None, "pu", "domega/dt", "not in the model"))
        if "1" in c:
            params.append(
                PhysicalParameter(
                    "constant term",
                    float(c["1"](theta_j)),
                    None,
                    "1/s",
                    "domega/dt",
                    "not mapped: D/M of an (omega - 1) form plus P_m/M if P_m is constant",
                )
            )

    def lag(state, tname, gains):
        if not ok.get(state):
            return None
        c = eq[state]
        src = f"d{state}/dt"
        tc = lambda t, c=c: -1.0 / c[state](t)  # noqa: E731
        add(tname, tc, "s", src, f"-1/c({state})")
        for u, gname, sign, second in gains:
            if u in c and gname:
                add(
                    gname,
                    lambda t, c=c, u=u, sign=sign: sign * c[u](t) * tc(t),
                    "pu",
                    src,
                    f"{'-' if sign < 0 else ''}c({u}) {tname}",
                )
            if u in c and second:
                add(
                    f"{tname} (from {u})",
                    lambda t, c=c, u=u: 1.0 / c[u](t),
                    "s",
                    src,
                    f"second estimate: 1/c({u})",
                )
        return c

    if ok.get("e_qp") and "v_q" in eq["e_qp"]:  # the terminal-voltage form
        c = eq["e_qp"]
        add("T'_d0", lambda t, c=c: 1.0 / c["v_f"](t), "s", "de_qp/dt", "1/c(v_f)")
        add(
            "x_d / x'_d",
            lambda t, c=c: 1.0 + c["v_q"](t) / c["v_f"](t),
            "",
            "de_qp/dt",
            "1 + c(v_q)/c(v_f) (v_q for i_d through the stator equation)",
        )
        add(
            "x_d / x'_d (from e_qp)",
            lambda t, c=c: -c["e_qp"](t) / c["v_f"](t),
            "",
            "de_qp/dt",
            "second estimate: -c(e_qp)/c(v_f)",
        )
    else:
        lag("e_qp", "T'_d0", [("i_d", "x_d - x'_d", -1.0, False), ("v_f", None, 1.0, True)])
    gq = "x_q - x'_q - gamma_q" if psat else "x_q - x'_q"
    lag("e_dp", "T'_q0", [("i_q", gq, 1.0, False)])
    lag(
        "e_dpp", "T''_q0", [("i_q", "x'_q - x'_d + gamma_q", 1.0, False), ("e_dp", None, 1.0, True)]
    )
    lag(
        "e_qpp",
        "T''_d0",
        [("i_d", "x'_d - x''_d + gamma_d", -1.0, False), ("e_qp", None, 1.0, True)],
    )

    # stator lines
    notes = [*(f"parameter inside a function: `{n}`" for n in de_notes + ae_notes), *set_aside]
    x_d_fn = None
    if ae is not None and family is not None:
        e_d = {"psat-5.1": "e_dpp", "two-axis": "e_dp"}.get(family)
        e_q = "1" if family == "classical" else "e_qp"
        xq_name = {
            "psat-5.1": "x'_d (q axis)",
            "two-axis": "x'_q",
            "one-axis": "x_q",
            "classical": "x'_d (q axis)",
        }[family]
        forms = {
            "i_d": ({"v_q", e_q}, {"v_d"} | ({e_d} if e_d else set())),
            "i_q": ({"v_d"} | ({e_d} if e_d else set()), {"v_q", e_q}),
        }
        ae_eq = dict(zip(ae.contract.targets, ae_lines, strict=True))
        pair: dict[str, Callable] = {}

        def mean_pair(c, state, volt, sign):
            """sign * (c(state) - c(volt)) / 2, or the one that is there. The classical
            stator's e_q is the constant E' (state ``"1"``): its coefficient is E' times the
            voltage's, so only the voltage's is used."""
            if state == "1":
                state = None
            if state and state in c and volt in c:
                return lambda t: sign * (c[state](t) - c[volt](t)) / 2
            if volt in c:
                return lambda t: -sign * c[volt](t)
            if state and state in c:
                return lambda t: sign * c[state](t)
            return lambda t: 0.0 * t[0]

        for y in ae.contract.targets:
            c = ae_eq[y]
            if y not in forms:
                if c is not None:
                    matches.append(
                        EquationMatch(y, tuple(sorted(c)), True, note="not used for parameters")
                    )
                continue
            if c is None:
                matches.append(EquationMatch(y, (), False, note="a parameter inside a function"))
                continue
            required, optional = forms[y]
            m = _check(y, c, frozenset(required), frozenset(optional))
            matches.append(m)
            if not m.matched:
                continue
            if y == "i_d":
                pair["ra_d"] = mean_pair(c, e_d, "v_d", 1.0)
                pair["xq"] = mean_pair(c, e_q, "v_q", 1.0)
            else:
                pair["ra_q"] = mean_pair(c, e_q, "v_q", 1.0)
                pair["xd"] = mean_pair(c, e_d, "v_d", -1.0)
        if "ra_d" in pair or "ra_q" in pair:
            if "ra_d" in pair and "ra_q" in pair:
                a = lambda t: (pair["ra_d"](t) + pair["ra_q"](t)) / 2  # noqa: E731
            else:
                a = pair.get("ra_d") or pair["ra_q"]
            bq = pair.get("xq") or pair.get("xd")
            bd = pair.get("xd") or pair.get("xq")
            det = lambda t: 1.0 / (a(t) ** 2 + bq(t) * bd(t))  # noqa: E731
            both = "xq" in pair and "xd" in pair
            src = "i_d, i_q" if both else ("i_d" if "xq" in pair else "i_q")
            if both or family in ("psat-5.1", "classical"):
                x_d_fn = lambda t: bd(t) * det(t)  # noqa: E731
                add(
                    "x'_d",
                    x_d_fn,
                    "pu",
                    src,
                    "stator d-axis reactance" + ("" if both else "; X_d = X_q assumed"),
                )
                if both:
                    add(xq_name, lambda t: bq(t) * det(t), "pu", src, "stator q-axis reactance")
                add("r_a", lambda t: a(t) * det(t), "pu", src, "stator resistance")
            else:
                notes.append(
                    f"the {family} stator has X_d != X_q: both i_d and i_q lines are "
                    "needed to map r_a and the reactances"
                )

    # derived across equations
    if (
        psat
        and x_d_fn is not None
        and "x_q - x'_q - gamma_q" in {entry[1] for entry in pending}
        and "x'_q - x'_d + gamma_q" in {entry[1] for entry in pending}
    ):
        ce, cpp = eq["e_dp"], eq["e_dpp"]
        g1 = lambda t: ce["i_q"](t) * (-1.0 / ce["e_dp"](t))  # noqa: E731
        g2 = lambda t: cpp["i_q"](t) * (-1.0 / cpp["e_dpp"](t))  # noqa: E731
        xq = lambda t: g1(t) + g2(t) + x_d_fn(t)  # noqa: E731
        add("x_q", xq, "pu", "de'_d/dt, de''_d/dt, stator", "gains of e'_d and e''_d plus x'_d")

        def xqp(t):
            cc = x_d_fn(t) * ce["e_dp"](t) / cpp["e_dpp"](t)  # x'_d T''_q0 / T'_q0
            b = xq(t) - g1(t) + cc
            return (b + jnp.sqrt(jnp.maximum(b * b - 4 * cc * xq(t), 0.0))) / 2

        add(
            "x'_q",
            xqp,
            "pu",
            "de'_d/dt, de''_d/dt, stator",
            "larger root of x'_q^2 - x'_q (x_q - a + c) + c x_q = 0",
        )

    if family is not None and partial:
        states = dict(_FAMILIES)[family]
        rest = ", ".join(f"d{t}/dt" for t in targets if t not in states)
        notes.insert(
            0,
            f"{family}: the largest family whose equations all match; outside it: {rest} "
            "(those that match their own form are still mapped)",
        )
    if family is None:
        notes.insert(
            0,
            "no family: "
            + "; ".join(
                f"{m.equation} has {', '.join(m.unmatched) or 'no extra term'}"
                + (f", lacks {', '.join(m.missing)}" if m.missing else "")
                for m in matches
                if not m.matched
            ),
        )
    if pending:
        fns = [entry[2] for entry in pending]

        def mapped(t: jax.Array) -> jax.Array:
            return jnp.stack([jnp.asarray(fn(t), dtype=jnp.float64) for fn in fns])

        values, jac = jax.jit(lambda t: (mapped(t), jax.jacrev(mapped)(t)))(theta_j)
        for (i, name, _, unit, source, note), value, grad in zip(
            pending, np.asarray(values), np.asarray(jac), strict=True
        ):
            params[i] = PhysicalParameter(name, float(value), stderr(grad), unit, source, note)
    return PhysicalReport(family, tuple(params), tuple(matches), tuple(notes))  # type: ignore[arg-type]


# ----------------------------------------------------------------------------------------------
# the pipeline's section


def discovery_section(discovery: Any) -> tuple[str, dict[str, Any]]:
    """The physical-parameter section of a :class:`jaxdmd.pipeline.Discovery` (:func:`section`
    of its equations; standard errors from the loops' final search states' problems when they
    are known). Never raises: a failure is reported in the section."""
    try:
        de_state = getattr(discovery, "de_state", None)
        ae_state = getattr(discovery, "ae_state", None)
        de, ae = discovery.de, discovery.ae
    except Exception as err:  # a report must not stop the pipeline
        return _failed(err)
    return section(
        de,
        ae,
        de_state.problem if de_state is not None else None,
        ae_state.problem if ae_state is not None else None,
    )


def section(
    de: Equations,
    ae: Equations | None = None,
    de_problem: Problem | None = None,
    ae_problem: Problem | None = None,
) -> tuple[str, dict[str, Any]]:
    """The physical-parameter section of discovered equations: Markdown for the top of
    ``equations.md`` and the JSON-ready dict for ``summary.json``
    (:func:`physical_parameters`; the problems, when given, for standard errors). Never raises:
    a failure is reported in the section."""
    try:
        rep = physical_parameters(de, ae, de_problem, ae_problem)
        return rep.markdown(), rep.to_dict()
    except Exception as err:  # a report must not stop the pipeline
        return _failed(err)


def _failed(err: Exception) -> tuple[str, dict[str, Any]]:
    text = f"could not map physical parameters: {type(err).__name__}: {err}"
    return f"## Physical parameters\n\n{text}\n", {"family": None, "error": text}


def with_section(markdown: str, section: str) -> str:
    """``markdown`` (``equations.md``) with ``section`` put first, after its ``#`` title."""
    head, sep, rest = markdown.partition("\n\n")
    if head.startswith("# ") and sep:
        return f"{head}\n\n{section.rstrip()}\n\n{rest}"
    return f"{section.rstrip()}\n\n{markdown}"
