"""The built-in offline proposer: a term-level evolutionary search that writes skeleton text.

It reads the same request a language model reads (the contract with its variable library, and
in-context examples with their scores and per-equation losses) and answers with skeleton source
and, like a model, a JSON block of variable requests. It knows no target equation: it edits the
examples' equations term by term, drawing new terms from a grammar of generic building blocks
over whatever variables the contract names:

- each variable; for a per-unit quantity that sits near 1 (a speed, a voltage) its deviation
  ``(x - 1)`` instead;
- for angles (unit ``rad``): sines and cosines of their differences (of the angle itself when
  there is only one);
- for a magnitude/angle pair on the boundary (a phasor such as V, theta): its projections
  ``V * sin(a - theta)``, ``V * cos(a - theta)`` onto every other angle a (a Park transform);
- products of two such blocks, and the constant.

Operators (one to three per sample, drawn at random): add a term, grow an equation by greedy
forward selection, remove the least useful term, swap a term, simplify (condense powers of one
variable into one rate form of it where that fits no worse, then backward elimination), take
the best small subset of blocks, prune terms whose fitted effect is negligible, and cross over
equations between two parents (each equation from the parent with the lower loss on it). New
terms are drawn from a softmax over how much of the equation's residual each explains once the
terms already present are projected out (with some uniform exploration), on a subsample of the
data the proposer was built with. A term is admitted, and backward elimination keeps it, only if
it lowers the equation's leave-one-recording-out error (when the data hold several recordings)
by a few per cent: a term that only fits the noise of one recording does not help predict
another. Variable requests rank the catalog variables outside the library by the explained
share; a boundary phasor (a magnitude and an angle, both outside) is ranked as one candidate and
requested as a pair, since its projections need both. Deterministic given the request's seed.
"""

from __future__ import annotations

import ast
import itertools
import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from jaxdmd import lines as ln
from jaxdmd import ties
from jaxdmd.prompts import Contract, PromptRequest, Variable
from jaxdmd.proposers import Sample
from jaxdmd.search import Problem
from jaxdmd.ties import settled

NOTHING = 1e-9  # a share of the error explained below this is rounding, not a term's effect

_NUMPY = {
    "sin": np.sin,
    "cos": np.cos,
    "tan": np.tan,
    "exp": np.exp,
    "log": np.log,
    "sqrt": np.sqrt,
    "tanh": np.tanh,
    "sinh": np.sinh,
    "cosh": np.cosh,
    "arctan": np.arctan,
    "arctan2": np.arctan2,
    "abs": np.abs,
    "where": np.where,
    "clip": np.clip,
    "maximum": np.maximum,
    "minimum": np.minimum,
    "sign": np.sign,
    "square": np.square,
}
_BINOPS = {
    ast.Add: np.add,
    ast.Sub: np.subtract,
    ast.Mult: np.multiply,
    ast.Div: np.divide,
    ast.Pow: np.power,
}
_CMP = {
    ast.Lt: np.less,
    ast.LtE: np.less_equal,
    ast.Gt: np.greater,
    ast.GtE: np.greater_equal,
    ast.Eq: np.equal,
    ast.NotEq: np.not_equal,
}


def evaluate(node: ast.AST, data: Mapping[str, np.ndarray]) -> np.ndarray:
    """Evaluate a parameter-free expression of a checked skeleton with NumPy."""
    if isinstance(node, ast.Expression):
        return evaluate(node.body, data)
    if isinstance(node, ast.Constant) and isinstance(node.value, int | float):
        return np.asarray(float(node.value))
    if isinstance(node, ast.Name):
        if node.id == "pi":
            return np.asarray(np.pi)
        return data[node.id]
    if isinstance(node, ast.Attribute) and node.attr == "pi":
        return np.asarray(np.pi)
    if isinstance(node, ast.BinOp) and type(node.op) in _BINOPS:
        return _BINOPS[type(node.op)](evaluate(node.left, data), evaluate(node.right, data))
    if isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.USub | ast.UAdd):
        value = evaluate(node.operand, data)
        return -value if isinstance(node.op, ast.USub) else value
    if isinstance(node, ast.Call):
        name = node.func.attr if isinstance(node.func, ast.Attribute) else node.func.id
        return _NUMPY[name](*(evaluate(a, data) for a in node.args))
    if isinstance(node, ast.IfExp):
        return np.where(
            evaluate(node.test, data), evaluate(node.body, data), evaluate(node.orelse, data)
        )
    if isinstance(node, ast.Compare) and len(node.ops) == 1:
        return _CMP[type(node.ops[0])](
            evaluate(node.left, data), evaluate(node.comparators[0], data)
        )
    raise ValueError(f"cannot evaluate {ast.unparse(node)}")


# ----------------------------------------------------------------------------------------------
# equations as term lists


def _is_param(node: ast.AST) -> bool:
    return (
        isinstance(node, ast.Subscript)
        and isinstance(node.value, ast.Name)
        and (node.value.id == "p")
    )


def _has_param(node: ast.AST) -> bool:
    return any(_is_param(n) for n in ast.walk(node))


def _factors(node: ast.expr) -> list[ast.expr]:
    if isinstance(node, ast.BinOp) and isinstance(node.op, ast.Mult):
        return [*_factors(node.left), *_factors(node.right)]
    return [node]


def _strip(node: ast.expr) -> str | None:
    """The term of a summand ``coefficient * term`` (the coefficient a parameter or constant)."""
    if isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.USub | ast.UAdd):
        return _strip(node.operand)
    if not _has_param(node):
        if isinstance(node, ast.Constant):
            return "1"
        return ast.unparse(node)
    if _is_param(node):
        return "1"
    if isinstance(node, ast.BinOp) and isinstance(node.op, ast.Div):
        if _has_param(node.right):
            return None
        top = _strip(node.left)
        if top is None:
            return None
        return ast.unparse(node.right) if top == "1" else f"{wrap(top)} / {_wrap_den(node.right)}"
    factors = _factors(node)
    params = [f for f in factors if _is_param(f)]
    rest = [f for f in factors if not _is_param(f)]
    if len(params) != 1 or any(_has_param(f) for f in rest):
        return None
    rest = [f for f in rest if not isinstance(f, ast.Constant)]
    if not rest:
        return "1"
    return " * ".join(wrap(ast.unparse(f)) for f in rest)


def _power_of(term: str) -> str | None:
    """The variable ``term`` is a power of (``x``, ``x * x``, ``x * x * x``), else None."""
    factors = _factors(ast.parse(term, mode="eval").body)
    if not all(isinstance(f, ast.Name) for f in factors):
        return None
    names = {f.id for f in factors}  # type: ignore[attr-defined]
    return names.pop() if len(names) == 1 else None


def wrap(text: str) -> str:
    """``text`` in parentheses where it is a sum or difference (a factor of a product)."""
    tree = ast.parse(text, mode="eval").body
    if isinstance(tree, ast.BinOp) and isinstance(tree.op, ast.Add | ast.Sub):
        return f"({text})"
    return text


def _wrap_den(node: ast.expr) -> str:
    text = ast.unparse(node)
    return f"({text})" if isinstance(node, ast.BinOp) else text


@dataclass(frozen=True)
class Equation:
    """A target's equation: a sum of terms with one coefficient each, or an opaque line."""

    terms: tuple[str, ...] = ()
    opaque: ln.Line | None = None

    def render(self) -> ln.Line:
        if self.opaque is not None:
            return self.opaque
        parts = [
            f"p[{k}]" if term == "1" else f"p[{k}] * {wrap(term)}"
            for k, term in enumerate(self.terms)
        ]
        expr = ast.parse(" + ".join(parts) if parts else "0.0 * p[0]", mode="eval").body
        return ln.Line(expr, max(len(self.terms), 1))


def parse_equations(source: str) -> list[Equation]:
    """The equations of a checked skeleton as term lists (opaque where not linear in p)."""
    lines, _ = ln.split_lines(source)
    out = []
    for line in lines:
        terms = [_strip(s) for s in ln.summands(line.expr)]
        if any(t is None for t in terms):
            out.append(Equation(opaque=line))
        else:
            unique = tuple(dict.fromkeys(t for t in terms if t is not None))
            out.append(Equation(terms=unique))
    return out


# ----------------------------------------------------------------------------------------------
# the grammar


def _near_one(values: np.ndarray) -> bool:
    return bool(abs(np.mean(values) - 1.0) < 0.1 and np.std(values) < 0.1)


def building_blocks(
    variables: Sequence[Variable], data: Mapping[str, np.ndarray]
) -> tuple[list[str], list[str]]:
    """Level-one blocks (usable in products) and angle terms (used alone) for these variables."""
    angles = [v.name for v in variables if v.unit == "rad"]
    blocks = _polynomial_blocks(variables, data)
    if len(angles) >= 2:
        for a, b in itertools.combinations(angles, 2):
            blocks += [f"jnp.sin({a} - {b})", f"jnp.cos({a} - {b})"]
    else:
        for a in angles:
            blocks += [f"jnp.sin({a})", f"jnp.cos({a})"]
    magnitudes = [v.name for v in variables if v.role == "boundary" and v.unit != "rad"]
    boundary_angles = [v.name for v in variables if v.role == "boundary" and v.unit == "rad"]
    for m, theta in itertools.product(magnitudes, boundary_angles):
        for a in angles:
            if a != theta:
                blocks += [f"{m} * jnp.sin({a} - {theta})", f"{m} * jnp.cos({a} - {theta})"]
    return blocks, angles


def term_pool(variables: Sequence[Variable], data: Mapping[str, np.ndarray]) -> list[str]:
    """All candidate terms: the constant, angles, level-one blocks and their pairwise products."""
    blocks, angles = building_blocks(variables, data)
    pool = ["1", *angles, *blocks]
    pool += [
        f"{wrap(a)} * {wrap(b)}" for a, b in itertools.combinations_with_replacement(blocks, 2)
    ]
    return list(dict.fromkeys(pool))


# the second tier: richer forms, offered for an equation only once the first (``term_pool``) has
# nothing left that passes the admission bar there (simplest forms first)
DIMENSIONLESS = ("", "1")  # units whose values may enter a function other than a power
TIME = "s"  # the unit of a time channel: periodic forcings sin(w t), cos(w t)
# forms with one rate r fitted by the proposer (written as a literal once refined on the data)
RATE_FORMS = (
    "jnp.exp({r} * {v})",
    "{v} * jnp.exp({r} * {v})",
    "jnp.tanh({r} * {v})",
    "{v} / (1 + jnp.abs({r} * {v}))",
)
TIME_FORMS = ("jnp.sin({r} * {v})", "jnp.cos({r} * {v})")
_RATE_GRID = tuple(s * 2.0**k for s in (-1, 1) for k in range(-2, 2))  # x 1 / max|v|
_CYCLES = tuple(2.0 ** (k / 2) for k in range(13))  # x 2 pi / duration: 1 to 64 cycles


@dataclass(frozen=True)
class Rated:
    """A second-tier term with a rate: its form, variable and rate."""

    form: str
    variable: str
    rate: float

    @property
    def term(self) -> str:
        return self.form.format(r=_literal(self.rate), v=self.variable)


def _literal(value: float) -> str:
    return f"{value:.4g}"


def _rate_grid(form: str, variable: str, scale: float) -> list[Rated]:
    """``form`` of ``variable`` at each rate of ``_RATE_GRID`` over ``scale`` (its largest
    magnitude), to three digits."""
    return [Rated(form, variable, float(f"{r / scale:.3g}")) for r in _RATE_GRID]


def _polynomial_blocks(variables: Sequence[Variable], data: Mapping[str, np.ndarray]) -> list[str]:
    """The level-one blocks that are a variable or its deviation (no function applied): each
    variable but angles (they enter through sines and cosines) and times (as forcings), a
    per-unit one that stays near 1 as its deviation ``(x - 1)``."""
    blocks = []
    for v in variables:
        if v.unit in ("rad", TIME):
            continue
        per_unit = v.unit in ("pu", "") and v.name in data
        blocks.append(f"({v.name} - 1)" if per_unit and _near_one(data[v.name]) else v.name)
    return blocks


def second_tier(
    variables: Sequence[Variable],
    data: Mapping[str, np.ndarray],
    degree: int = 3,
    blocks: Sequence[str] = (),
) -> tuple[list[str], dict[str, Rated]]:
    """Richer candidate terms: monomials of degree 3 to ``degree`` of the variables (and their
    deviations); for dimensionless variables their sines and cosines, times each variable too,
    and the rate forms of ``RATE_FORMS`` on a grid of rates; for a time channel (unit ``s``)
    sines and cosines on a grid of frequencies; and the user's ``blocks`` (expressions in the
    variables' names, a ``{v}`` in one standing for each variable but angles and times; those
    naming a variable not offered are left out). Returns the terms and the rated ones' forms
    (their rates are refined on the data when drawn)."""
    poly = _polynomial_blocks(variables, data)
    terms = [
        " * ".join(wrap(b) for b in combo)
        for k in range(3, degree + 1)
        for combo in itertools.combinations_with_replacement(poly, k)
    ]
    names = {v.name for v in variables}
    plain = [v.name for v in variables if v.unit not in ("rad", TIME)]
    for block in blocks:
        for text in [block.format(v=n) for n in plain] if "{v}" in block else [block]:
            used = {n.id for n in ast.walk(ast.parse(text, mode="eval")) if isinstance(n, ast.Name)}
            if used - {"jnp", "pi"} <= names:
                terms.append(text)
    rated: dict[str, Rated] = {}
    for v in variables:
        if v.name not in data or v.unit == "rad":
            continue
        values = np.asarray(data[v.name], dtype=float)
        if v.unit in DIMENSIONLESS:
            trig = [f"jnp.sin({v.name})", f"jnp.cos({v.name})"]
            terms += trig + [f"{wrap(b)} * {f}" for f in trig for b in poly]
            scale = float(np.max(np.abs(values)))
            if scale > 0:
                for form in RATE_FORMS:
                    rated.update((item.term, item) for item in _rate_grid(form, v.name, scale))
        elif v.unit == TIME:
            span = float(np.ptp(values))
            if span > 0:
                for form in TIME_FORMS:
                    for c in _CYCLES:
                        item = Rated(form, v.name, float(f"{2 * np.pi * c / span:.3g}"))
                        rated[item.term] = item
    terms += list(rated)
    return list(dict.fromkeys(terms)), rated


def subset_errors(
    x: np.ndarray, y: np.ndarray, folds: Sequence[np.ndarray], max_size: int
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Every subset of the columns of ``x`` [n, B] as regressors of ``y`` [n], by size: for
    k = 1 .. ``max_size``, the subsets ``[S, k]`` and their held-out sums of squared errors
    ``[S]`` (least squares with a tiny ridge, fitted with each fold of ``folds``, boolean masks,
    left out and scored on it; with one fold, fitted and scored on it). Exhaustive, so for a
    few dozen columns and small k."""
    gram = np.stack([x[f].T @ x[f] for f in folds])  # [F, B, B]
    cross = np.stack([x[f].T @ y[f] for f in folds])  # [F, B]
    yy = np.array([y[f] @ y[f] for f in folds])
    held_out = len(folds) > 1
    out = []
    for k in range(1, max_size + 1):
        subsets = np.array(list(itertools.combinations(range(x.shape[1]), k)))  # [S, k]
        g_sub = gram[:, subsets[:, :, None], subsets[:, None, :]]  # [F, S, k, k]
        c_sub = cross[:, subsets]  # [F, S, k]
        g_fit = g_sub.sum(0) - g_sub if held_out else g_sub
        c_fit = c_sub.sum(0) - c_sub if held_out else c_sub
        ridge = 1e-10 * np.trace(g_fit, axis1=-2, axis2=-1)[..., None, None] + 1e-300
        coef = np.linalg.solve(g_fit + ridge * np.eye(k), c_fit[..., None])[..., 0]
        sse = (
            yy[:, None]
            - 2 * np.einsum("fsk,fsk->fs", coef, c_sub)
            + np.einsum("fsk,fskl,fsl->fs", coef, g_sub, coef)
        ).sum(0)
        out.append((subsets, sse))
    return out


# ----------------------------------------------------------------------------------------------
# the proposer

# edits of one equation per step, and how often each is drawn: add a ranked term, grow greedily,
# remove, swap, simplify (backward elimination), and subset: the best small subset of the
# level-one blocks, found exhaustively (a sparse linear model, the first thing an engineer fits)
_OPERATORS = ("add", "grow", "remove", "swap", "simplify", "subset")
_OPERATOR_WEIGHTS = (0.3, 0.25, 0.1, 0.15, 0.1, 0.1)


@dataclass(frozen=True)
class OfflineConfig:
    max_samples: int = 3000  # subsample of the data used to rank terms
    explore: float = 0.25  # probability of drawing a new term uniformly instead of by rank
    rank_temperature: float = 0.1  # softmax temperature over normalised explained fractions
    grow_terms: int = 4  # terms added by one greedy growth
    min_gain: float = 1e-4  # a term must lower the equation's NMSE by this much to be added
    # ... and by this share of it: with smoothed derivative targets the samples are strongly
    # correlated (a window holds ~25 of them), so a BIC-like penalty log(n_eff) / n_eff with
    # n_eff ~ n / 25 is a few per cent; terms below it mostly fit the noise of the estimates
    min_relative_gain: float = 0.02
    prune_effect: float = 2e-3  # prune a term whose fitted effect is below this (x target std)
    max_terms: int = 8  # terms per equation
    max_requests: int = 2  # variables requested per answer (each the best for its equation)
    min_request_gain: float = 1e-3  # NMSE drop a requested variable's best term must bring
    subset_size: int = 3  # the "subset" edit searches every subset of up to this many blocks
    degree: int = 3  # the second tier's largest monomial degree (2: no monomials beyond pairs)
    # the user's building blocks, joining the second tier: expressions in the variables' names
    # (jnp functions as in a skeleton), "{v}" standing for each variable, e.g. "{v} / (1 + {v}**2)"
    blocks: tuple[str, ...] = ()


def _shares(residual: np.ndarray, q: np.ndarray | None, phi: np.ndarray) -> np.ndarray:
    """Share of ``residual`` each column of ``phi`` explains once the span of ``q`` (an
    orthonormal basis, or None) is projected out of it."""
    if q is not None:
        phi = phi - q @ (q.T @ phi)
    norms = np.einsum("ij,ij->j", phi, phi)
    rr = float(residual @ residual) + 1e-300
    return np.where(norms > 1e-12 * len(residual), (residual @ phi) ** 2 / (norms * rr), 0)


class OfflineProposer:
    """The default proposer; built with the data it may look at (like an engineer at a plot)."""

    def __init__(
        self,
        variables: Mapping[str, np.ndarray],
        targets: np.ndarray,
        catalog: Sequence[Variable] = (),
        config: OfflineConfig | None = None,
        weights: np.ndarray | None = None,
        operator: tuple[np.ndarray, np.ndarray] | None = None,
        groups: np.ndarray | None = None,
    ):
        self.config = config or OfflineConfig()
        targets = np.asarray(targets, dtype=float)
        n = targets.shape[1]
        stride = max(1, int(np.ceil(n / self.config.max_samples)))
        index = np.arange(0, n, stride)
        w = None
        if weights is not None:
            w = np.asarray(weights, dtype=float)
            w = w.reshape(-1, w.shape[-1]).mean(axis=0) if w.ndim > 1 else w
            w = np.broadcast_to(w, (n,))
            index = index[w[index] > 0]
        # terms are evaluated on all samples (the operator mixes neighbours), then subsampled
        self.full = {k: np.asarray(v, dtype=float) for k, v in variables.items()}
        self.data = {k: v[index] for k, v in self.full.items()}
        self.index = index
        self.operator = operator
        # weighted least squares throughout: rows scaled by the square roots of the weights
        self.root_w = np.ones(len(index)) if w is None else np.sqrt(w[index])
        self.targets = targets[:, index] * self.root_w
        # recordings of the subsample: terms are admitted by their leave-one-recording-out error
        self.groups = None if groups is None else np.asarray(groups)[index]
        if self.groups is not None and len(np.unique(self.groups)) < 2:
            self.groups = None
        self.scale = self.targets.std(axis=1) + 1e-300
        self.catalog = tuple(catalog)
        self._cache: dict[str, np.ndarray | None] = {}
        self._tiers: dict[tuple[Variable, ...], tuple[list[str], list[str]]] = {}
        self._pools: dict[tuple[Variable, ...], list[str]] = {}
        self._held_out: dict[tuple[int, tuple[str, ...]], float] = {}
        self._rated: dict[str, Rated] = {}

    @classmethod
    def for_problem(cls, problem: Problem, config: OfflineConfig | None = None) -> OfflineProposer:
        """Build from a loop's :class:`jaxdmd.search.Problem` (its data, operator, recordings)."""
        op = problem.operator
        return cls(
            {k: np.asarray(v) for k, v in problem.variables.items()},
            np.asarray(problem.targets),
            problem.catalog,
            config,
            None if problem.weights is None else np.asarray(problem.weights),
            None if op is None else (np.asarray(op.index), np.asarray(op.weight)),
            None if problem.groups is None else np.asarray(problem.groups),
        )

    # -- numerics --------------------------------------------------------------------------

    def column(self, term: str) -> np.ndarray | None:
        if term not in self._cache:
            self._cache[term] = self._evaluate(term)
        return self._cache[term]

    def _evaluate(self, term: str) -> np.ndarray | None:
        """The term's column on the subsample (after the operator, weighted); None if it is
        not finite or identically zero."""
        try:
            n = len(next(iter(self.full.values())))
            with np.errstate(all="ignore"):
                value = np.broadcast_to(
                    evaluate(ast.parse(term, mode="eval"), self.full), (n,)
                ).astype(float)
            if self.operator is not None:
                index, weight = self.operator
                value = np.sum(value[index] * weight, axis=1)
            value = value[self.index] * self.root_w
            ok = np.all(np.isfinite(value)) and np.std(value) + abs(np.mean(value)) > 0
            return value if ok else None
        except (ValueError, KeyError, TypeError, ZeroDivisionError):
            return None

    def tiers(self, variables: Sequence[Variable]) -> tuple[list[str], list[str]]:
        """The first tier (:func:`term_pool`) and the second (:func:`second_tier`) for these
        variables, built once per variable set."""
        key = tuple(variables)
        if key not in self._tiers:
            extra, rated = second_tier(variables, self.data, self.config.degree, self.config.blocks)
            self._rated.update(rated)
            self._tiers[key] = (self.pool(variables), extra)
        return self._tiers[key]

    def pool(self, variables: Sequence[Variable]) -> list[str]:
        """:func:`term_pool` of these variables on the proposer's data, built once."""
        key = tuple(variables)
        if key not in self._pools:
            self._pools[key] = term_pool(variables, self.data)
        return self._pools[key]

    def design(self, terms: Sequence[str]) -> np.ndarray:
        cols = [self.column(t) for t in terms]
        cols = [c for c in cols if c is not None]
        return np.stack(cols, axis=1) if cols else np.zeros((self.targets.shape[1], 0))

    def solve(self, j: int, terms: Sequence[str]) -> tuple[np.ndarray, np.ndarray, float]:
        """Least-squares coefficients, residual and NMSE of equation j with these terms."""
        y = self.targets[j]
        x = self.design(terms)
        if x.shape[1] == 0:
            return np.zeros(0), y, float(np.mean(y**2) / self.scale[j] ** 2)
        coef, *_ = np.linalg.lstsq(x, y, rcond=None)
        residual = y - x @ coef
        return coef, residual, float(np.mean(residual**2) / self.scale[j] ** 2)

    def held_out(self, j: int, terms: Sequence[str]) -> float:
        """Leave-one-recording-out NMSE of equation j with these terms (training NMSE if the
        data are one recording): the measure by which terms are admitted and dropped. Kept
        once computed: the operators ask it of the same equation many times."""
        key = (j, tuple(terms))
        if key not in self._held_out:
            self._held_out[key] = self._loro(j, terms)
        return self._held_out[key]

    def _loro(self, j: int, terms: Sequence[str]) -> float:
        if self.groups is None:
            return self.solve(j, terms)[2]
        y = self.targets[j]
        x = self.design(terms)
        if x.shape[1] == 0:
            return float(np.mean(y**2) / self.scale[j] ** 2)
        sse = 0.0
        for g in np.unique(self.groups):
            held = self.groups == g
            coef, *_ = np.linalg.lstsq(x[~held], y[~held], rcond=None)
            sse += float(np.sum((y[held] - x[held] @ coef) ** 2))
        return sse / len(y) / self.scale[j] ** 2

    def fitted(self, j: int, terms: Sequence[str]) -> tuple[np.ndarray, np.ndarray | None, float]:
        """Equation j fitted with ``terms``: its residual, an orthonormal basis of the terms'
        columns (None without any) and its NMSE; what :meth:`explained` projects out."""
        _, residual, loss = self.solve(j, terms)
        x = self.design(terms)
        return residual, np.linalg.qr(x)[0] if x.shape[1] else None, loss

    def explained(self, j: int, terms: Sequence[str], pool: Sequence[str]) -> np.ndarray:
        """Share of equation j's residual each pool term explains beyond ``terms``."""
        cand = [t for t in pool if self.column(t) is not None]
        if not cand:
            return np.zeros(0)
        residual, q, _ = self.fitted(j, terms)
        share = _shares(residual, q, self.design(cand))
        out = np.zeros(len(pool))
        index = {t: i for i, t in enumerate(cand)}
        for i, t in enumerate(pool):
            if t in index:
                out[i] = share[index[t]]
        return out

    # -- operators -------------------------------------------------------------------------

    def _passes(self, j: int, terms: Sequence[str], term: str) -> bool:
        """Whether adding ``term`` lowers equation j's held-out error by the admission bar."""
        before = self.held_out(j, terms)
        after = self.held_out(j, [*terms, term])
        needed = max(self.config.min_gain, self.config.min_relative_gain * before)
        return settled(before - after) >= settled(needed)

    def _refine(self, j: int, terms: Sequence[str], term: str) -> str:
        """A rated term with its rate fitted to equation j's residual (bounded: within a
        factor sqrt 2 of the grid's rate for a frequency; for a rate within a factor 2 and with
        |r| max|x| between 1/8 and 4, where the form is not a polynomial in disguise); other
        terms as they are."""
        from scipy.optimize import minimize_scalar

        item = self._rated.get(term)
        if item is None:
            return term
        x = self.design(terms)
        y = self.targets[j]

        def loss(log_rate: float) -> float:
            rate = np.sign(item.rate) * np.exp(log_rate)
            column = self._evaluate(Rated(item.form, item.variable, rate).term)
            if column is None:
                return np.inf
            design = np.column_stack([x, column])
            coef, *_ = np.linalg.lstsq(design, y, rcond=None)
            return float(np.sum((y - design @ coef) ** 2))

        centre = np.log(abs(item.rate))
        if item.form in TIME_FORMS:
            low, high = centre - np.log(np.sqrt(2.0)), centre + np.log(np.sqrt(2.0))
        else:  # |r| max|x| within [1/8, 4]: below, the form is a polynomial in disguise
            scale = float(np.max(np.abs(self.data[item.variable])))
            low = max(centre - np.log(2.0), np.log(0.125 / scale))
            high = min(centre + np.log(2.0), np.log(4.0 / scale))
        found = minimize_scalar(
            loss,
            bounds=(low, high),
            method="bounded",
            options={"xatol": 1e-5},
        )
        rate = float(f"{np.sign(item.rate) * np.exp(found.x):.4g}")
        refined = Rated(item.form, item.variable, rate)
        self._rated[refined.term] = refined
        return refined.term

    def _siblings(self, terms: Sequence[str]) -> list[str]:
        """For each periodic forcing in ``terms``, its quadrature partner at the same frequency
        (a phase needs both)."""
        out = []
        for t in terms:
            item = self._rated.get(t)
            if item is not None and item.form in TIME_FORMS:
                out += [Rated(f, item.variable, item.rate).term for f in TIME_FORMS]
        return [t for t in dict.fromkeys(out) if t not in terms]

    def _add(self, rng, j, terms, pool, greedy=False, extra=()) -> list[str]:
        terms = list(terms)
        if len(terms) >= self.config.max_terms:
            return terms
        free = [t for t in pool if t not in terms]
        share = self.explained(j, terms, free)
        if extra and (
            not free
            or share.max() <= NOTHING
            or not self._passes(j, terms, free[ties.argmax(share)])
        ):
            # the first tier has nothing left for this equation: the second joins the draw
            # (a rated form once per variable: two rates of it fit rounding, not the system)
            present = {(r.form, r.variable) for r in map(self._rated.get, terms) if r}
            free += [
                t
                for t in (*self._siblings(terms), *extra)
                if t not in terms
                and t not in free
                and (
                    t not in self._rated
                    or (self._rated[t].form, self._rated[t].variable) not in present
                )
            ]
            share = self.explained(j, terms, free)
        if not free:
            return terms
        if greedy or rng.random() > self.config.explore:
            top = share.max()
            if top <= NOTHING:  # no term explains anything: rounding must not rank them
                return terms
            logits = (share / top - 1.0) / self.config.rank_temperature
            prob = np.exp(logits - logits.max())
            choice = (
                ties.argmax(share) if greedy else int(rng.choice(len(free), p=prob / prob.sum()))
            )
        else:
            choice = int(rng.integers(len(free)))
        term = self._refine(j, terms, free[choice])
        lucky = not greedy and rng.random() < 0.1  # drawn whatever the comparison says
        if self._passes(j, terms, term) or lucky:
            terms.append(term)
        return terms

    def _remove(self, rng, j, terms) -> list[str]:
        if len(terms) <= 1:
            return list(terms)
        if rng.random() < 0.5:
            drop = int(rng.integers(len(terms)))
        else:
            losses = [self.solve(j, terms[:i] + terms[i + 1 :])[2] for i in range(len(terms))]
            drop = ties.argmin(losses)
        return [t for i, t in enumerate(terms) if i != drop]

    def _prune(self, j, terms) -> list[str]:
        terms = list(terms)
        while len(terms) > 1:
            coef, _, _ = self.solve(j, terms)
            x = self.design(terms)
            if x.shape[1] != len(terms):
                return terms
            effect = np.abs(coef) * x.std(axis=0) / self.scale[j]
            effect[[t == "1" for t in terms]] = np.inf  # the offset is judged by removal below
            worst = ties.argmin(effect)
            if effect[worst] >= self.config.prune_effect:
                break
            terms.pop(worst)
        return terms

    def _simplify(self, j, terms) -> list[str]:
        """Backward elimination: drop terms whose removal costs less than the admission bar;
        first, :meth:`_condense` the powers of one variable into one rated form of it."""
        terms = self._condense(j, terms)
        while len(terms) > 1:
            base = self.held_out(j, terms)
            losses = [self.held_out(j, terms[:i] + terms[i + 1 :]) for i in range(len(terms))]
            i = ties.argmin(losses)
            if losses[i] - base > max(self.config.min_relative_gain * base, 1e-5):
                break
            terms.pop(i)
        return terms

    def _condense(self, j: int, terms: Sequence[str]) -> list[str]:
        """Powers of one variable (``x``, ``x * x``, ...: a truncated series) replaced by one
        rated form of it (``x * jnp.exp(r * x)``, ``jnp.tanh(r * x)``, ...) where that fits
        equation j no worse held out: fewer terms, and the form extrapolates as the data's
        shape does, not as its Taylor polynomial. The first tier's powers pass the admission
        bar before the second tier is offered; once they are in, the form alone explains too
        little more to be admitted, so without this move a series would stay. For each form
        the grid's rate that explains most of the rest's residual is refined; the best form
        wins (on a tie the earlier form, and a form over the powers: it is simpler)."""
        terms = list(terms)
        for name in sorted({r.variable for r in self._rated.values() if r.form in RATE_FORMS}):
            powers = [t for t in terms if _power_of(t) == name]
            if len(powers) < 2:
                continue
            rest = [t for t in terms if t not in powers]
            scale = float(np.max(np.abs(self.data[name])))
            best, error = terms, settled(self.held_out(j, terms))
            for form in RATE_FORMS:
                grid = _rate_grid(form, name, scale)
                for item in grid:
                    self._rated.setdefault(item.term, item)
                share = self.explained(j, rest, [item.term for item in grid])
                if share.max() <= NOTHING:
                    continue
                candidate = [*rest, self._refine(j, rest, grid[ties.argmax(share)].term)]
                found = settled(self.held_out(j, candidate))
                if found < error or (best is terms and found == error):
                    best, error = candidate, found
            terms = best
        return terms

    def _subset(self, rng, j: int, variables: Sequence[Variable]) -> list[str]:
        """A best subset of at most ``subset_size`` level-one blocks (the constant, angles,
        single variables or their deviations) for equation j, by held-out error over every
        subset: the smallest size whose best is within ``min_relative_gain`` of the best of any
        size, and of that size one subset drawn among those within that bar (near-equivalent
        variables, such as a state and a measured channel tied to it, are then all offered)."""
        blocks, angles = building_blocks(variables, self.data)
        names = [t for t in dict.fromkeys(["1", *angles, *blocks]) if self.column(t) is not None]
        if not names:
            return ["1"]
        x, y = self.design(names), self.targets[j]
        folds = (
            [np.ones(len(y), bool)]
            if self.groups is None
            else [self.groups == g for g in np.unique(self.groups)]
        )
        best = subset_errors(x, y, folds, min(self.config.subset_size, len(names)))
        bar = min(float(sse.min()) for _, sse in best) * (1 + self.config.min_relative_gain)
        for subsets, sse in best:  # by size: the first whose best is within the bar
            near = np.flatnonzero(sse <= bar)
            if near.size:
                return [names[i] for i in subsets[int(rng.choice(near))]]
        return ["1"]

    # -- proposing ---------------------------------------------------------------------------

    def propose(self, requests: Sequence[PromptRequest]) -> list[Sample]:
        samples = []
        for request in requests:
            rng = np.random.default_rng(request.seed)
            for _ in range(request.n_samples):
                text = self.answer(request, rng)
                samples.append(Sample(text=text, island=request.island, origin="offline"))
        return samples

    def answer(self, request: PromptRequest, rng: np.random.Generator) -> str:
        contract = request.contract
        variables = (*contract.states, *contract.library)
        pool, extra = self.tiers(variables)
        parents = [(ex, parse_equations(ex.source)) for ex in request.examples]
        n_out = len(contract.targets)
        if not parents:
            equations = [Equation(terms=("1",)) for _ in range(n_out)]
            losses = [1.0] * n_out
        else:
            # the better parents more often; examples come ordered worst to best
            weights = np.arange(1, len(parents) + 1, dtype=float) ** 2
            first = int(rng.choice(len(parents), p=weights / weights.sum()))
            equations = list(parents[first][1])
            losses = list(parents[first][0].losses) or [1.0] * n_out
            if len(parents) > 1 and rng.random() < 0.35:
                other = parents[int(rng.integers(len(parents)))]
                for j in range(n_out):
                    lucky = rng.random() < 0.1  # drawn whatever the comparison says
                    if settled(other[0].losses[j]) < settled(losses[j]) or lucky:
                        equations[j], losses[j] = other[1][j], other[0].losses[j]
        ops = int(rng.integers(1, 4))
        for _ in range(ops):
            weights = np.asarray(losses, dtype=float) + 1e-6
            j = int(rng.choice(n_out, p=weights / weights.sum()))
            eq = equations[j]
            if eq.opaque is not None:
                eq = Equation(terms=("1",))  # an opaque line is rebuilt from terms
            terms = list(eq.terms)
            op = rng.choice(_OPERATORS, p=_OPERATOR_WEIGHTS)
            if op == "subset":
                terms = self._subset(rng, j, variables)
            elif op == "add":
                terms = self._add(rng, j, terms, pool, extra=extra)
            elif op == "grow":
                for _ in range(int(rng.integers(1, self.config.grow_terms + 1))):
                    terms = self._add(rng, j, terms, pool, greedy=True, extra=extra)
            elif op == "remove":
                terms = self._remove(rng, j, terms)
            elif op == "swap":
                terms = self._add(rng, j, self._remove(rng, j, terms), pool, extra=extra)
            else:
                terms = self._simplify(j, terms)
            terms = self._prune(j, terms)
            _, _, loss = self.solve(j, terms)
            equations[j], losses[j] = Equation(terms=tuple(terms)), loss
        source = ln.assemble(
            contract.function_name,
            contract.arguments,
            [e.render() for e in equations],
            contract.outputs,
        )
        requests = self.variable_requests(contract, equations)
        answer = f"```python\n{source}```\n"
        if requests:
            answer += "```json\n" + json.dumps({"variables": requests}) + "\n```\n"
        return answer

    def variable_requests(
        self, contract: Contract, equations: Sequence[Equation]
    ) -> list[dict[str, str]]:
        """Catalog variables outside the library, ranked by the residual share they explain."""
        have = set(contract.arguments)
        outside = [v for v in self.catalog if v.name not in have and v.name in self.data]
        if not outside:
            return []
        base = (*contract.states, *contract.library)
        base_pool = set(self.pool(base))
        # candidates: each outside variable, and each boundary phasor (a magnitude and an angle,
        # both outside): its projections only exist once both are in, so it is judged as one
        groups: list[tuple[Variable, ...]] = [(v,) for v in outside]
        magnitudes = [v for v in outside if v.role == "boundary" and v.unit != "rad"]
        angles = [v for v in outside if v.role == "boundary" and v.unit == "rad"]
        groups += [(m, a) for m in magnitudes for a in angles]
        # for every equation, the candidate whose best term explains most of its error
        per_equation: dict[int, tuple[float, tuple[Variable, ...]]] = {}
        # each equation's fit with its own terms, shared by every candidate
        fits = [
            self.fitted(j, list(eq.terms) if eq.opaque is None else ["1"])
            for j, eq in enumerate(equations)
        ]
        for group in groups:
            pool = [t for t in self.pool((*base, *group)) if t not in base_pool]
            if not pool:  # a variable with no first-tier term (a time): judged by its second
                extra, rated = second_tier((*base, *group), self.data, self.config.degree)
                names = {v.name for v in group}
                pool = [t for t in extra if t in rated and rated[t].variable in names]
            phi = self.design([t for t in pool if self.column(t) is not None])
            for j, (residual, q, loss) in enumerate(fits):
                share = float(_shares(residual, q, phi).max(initial=0.0)) * min(loss, 1.0)
                if settled(share) > settled(per_equation.get(j, (0.0, group))[0]):
                    per_equation[j] = (share, group)
        scores = sorted(
            ((s, g, j) for j, (s, g) in per_equation.items()), key=lambda x: -settled(x[0])
        )
        out: list[dict[str, str]] = []
        seen: set[str] = set()
        n_requests = 0
        for share, group, j in scores:
            if n_requests >= self.config.max_requests or share < self.config.min_request_gain:
                break
            fresh = [v for v in group if v.name not in seen]
            if not fresh:
                continue
            n_requests += 1
            for v in fresh:
                seen.add(v.name)
                out.append(
                    {
                        "name": v.name,
                        "role": v.role,
                        "reason": f"explains {share:.1%} of the error of {contract.targets[j]}",
                    }
                )
        return out
