"""The discrepancy report: what a model gets wrong on a recording, why, and what fixes it.

Given recordings and the model an engineer has (a skeleton file with or without parameters, or
a built-in textbook machine model), :func:`diagnose`

1. simulates the model on held-out data (:mod:`jaxdmd.rollout`, ``mode="de"``: the measured
   algebraic variables, inputs and any state the model does not simulate are played in) and
   locates the error per state: before the first event, in the fault window, after it, and
   whether it drifts;
2. refits the model's parameters alone on the training data; if that removes the error and no
   term explains what is left, the cause is a *parameter* error;
3. otherwise ranks candidate terms, from the offline proposer's grammar over every measured
   channel, by the share of each equation's residual they explain *out of sample*
   (leave-one-recording-out least squares; with one recording, contiguous time blocks): the
   equation whose residual a single term explains best carries the error, and that term names
   the cause: a *missing variable* (it uses a channel the model lacks) or a *missing term* (it
   is built from the model's own variables);
4. extends the model: the search of :mod:`jaxdmd.search`, seeded with the (refitted) model, its
   first round offered the model plus the best-ranked term, variable extension allowed;
5. measures the gain: the same held-out rollout before and after.

Everything is computed from the data; the ranking knows no answer (the same generic grammar the
offline proposer draws from). :func:`jaxdmd.report.write_report` (re-exported here) writes
``report.md`` with plots and ``diagnosis.json`` (schema in ``docs/diagnose.md``).
"""

from __future__ import annotations

import ast
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxdmd import lines as ln
from jaxdmd import search
from jaxdmd.data import Dataset
from jaxdmd.pipeline import run_loop
from jaxdmd.problems import de_problem
from jaxdmd.proposers import Sample
from jaxdmd.proposers.offline import (
    OfflineProposer,
    parse_equations,
    term_pool,
    wrap,
)
from jaxdmd.report import report_markdown, write_report
from jaxdmd.rollout import Block, RolloutResult, as_block, fault_window, metrics, rollout
from jaxdmd.search import Equations, Problem, SearchConfig, SearchState
from jaxdmd.skeleton import Skeleton, SkeletonError, compile_skeleton, extract

__all__ = [
    "BUILTIN_MODELS",
    "Candidate",
    "Cause",
    "DiagnoseConfig",
    "Diagnosis",
    "UserModel",
    "builtin_model",
    "diagnose",
    "load_model",
    "parse_model",
    "report_markdown",  # re-exported from jaxdmd.report
    "unmeasured_inputs",
    "write_report",  # re-exported from jaxdmd.report
]

# ------------------------------------------------------------------------------------------------
# models
# ------------------------------------------------------------------------------------------------

# Textbook machine models in the benchmark's channel names, written affine in their parameters
# (every coefficient free: the machine data are fitted, not assumed). No damping and no
# saturation; the mechanical power P_m and the field voltage v_f are the measured inputs when the
# data have them, else constants folded into an offset. A damper, a saturation, a control the
# model ignores is what a diagnosis should then find.
_STATES: dict[str, tuple[str, ...]] = {
    "classical": ("delta", "omega"),
    "one-axis": ("delta", "omega", "e_qp"),
    "two-axis": ("delta", "omega", "e_qp", "e_dp"),
    "psat-5.1": ("delta", "omega", "e_qp", "e_dp", "e_dpp"),
}
BUILTIN_MODELS = tuple(_STATES)
"""Names of the built-in models (`builtin_model`)."""


def _builtin_source(name: str, inputs: frozenset[str]) -> str:
    """The built-in model's skeleton; ``inputs``: which of P_m, v_f the data measure."""
    p = iter(range(64))
    body = [f"    d_delta = p[{next(p)}] * omega + p[{next(p)}]  # Omega_b (omega - 1)"]
    pm = f"p[{next(p)}] * P_m" if "P_m" in inputs else f"p[{next(p)}]"
    body.append(f"    d_omega = {pm} + p[{next(p)}] * P_e  # (P_m - P_e) / M")
    states = _STATES[name]
    if "e_qp" in states:
        vf = f"p[{next(p)}] * v_f" if "v_f" in inputs else f"p[{next(p)}]"
        body.append(
            f"    d_e_qp = {vf} + p[{next(p)}] * e_qp + p[{next(p)}] * i_d"
            "  # (v_f - e'_q - (x_d - x'_d) i_d) / T'_d0"
        )
    if "e_dp" in states:
        body.append(
            f"    d_e_dp = p[{next(p)}] * e_dp + p[{next(p)}] * i_q"
            "  # (-e'_d + (x_q - x'_q) i_q) / T'_q0"
        )
    if "e_dpp" in states:
        body.append(
            f"    d_e_dpp = p[{next(p)}] * e_dpp + p[{next(p)}] * e_dp + p[{next(p)}] * i_q"
            "  # PSAT 5.1 sub-transient d axis"
        )
    used = ["omega", *(s for s in ("e_qp", "e_dp", "e_dpp") if s in states)]
    used += [v for v in ("P_m", "v_f") if v in inputs and (v == "P_m" or "e_qp" in states)]
    used += ["P_e", *(["i_d"] if "e_qp" in states else []), *(["i_q"] if "e_dp" in states else [])]
    outputs = ", ".join(f"d_{s}" for s in states)
    return (
        f"def equation({', '.join([*used, 'p'])}):\n"
        + "\n".join(body)
        + f"\n    return {outputs}\n"
    )


@dataclass(frozen=True)
class UserModel:
    """The model under test: a skeleton, the states it integrates, and optional parameters.

    ``params`` None means "fit them" (built-in models, files without parameters).
    """

    name: str
    source: str
    targets: tuple[str, ...]
    params: tuple[float, ...] | None = None

    @property
    def arguments(self) -> tuple[str, ...]:
        fdef = ast.parse(self.source).body[0]
        assert isinstance(fdef, ast.FunctionDef)
        return tuple(a.arg for a in fdef.args.args[:-1])

    def skeleton(self) -> Skeleton:
        return compile_skeleton(self.source, variables=self.arguments, n_outputs=len(self.targets))


def builtin_model(name: str, channels: Sequence[str] = ("P_m", "v_f")) -> UserModel:
    """A built-in model (``classical``, ``one-axis``, ``two-axis``, ``psat-5.1``).

    ``channels``: the data's channel names; P_m and v_f enter as inputs if they are among them.
    """
    from jaxdmd.grid.machines import canonical_model_name

    try:
        key = canonical_model_name(name)
    except ValueError:
        raise ValueError(
            f"unknown built-in model {name!r}; use one of {list(BUILTIN_MODELS)} or a .py file"
        ) from None
    source = _builtin_source(key, frozenset(channels) & {"P_m", "v_f"})
    return UserModel(name=key, source=source, targets=_STATES[key])


# The machine's inputs a model may lack: the equation each enters, what it is, and the model
# that would give its variation when it is not measured.
_INPUTS: dict[str, tuple[str, str, str]] = {
    "P_m": ("omega", "the mechanical power", "a governor model"),
    "v_f": ("e_qp", "the field voltage", "an exciter model"),
}


def unmeasured_inputs(model: UserModel, channels: Sequence[str]) -> dict[str, str]:
    """The inputs the model's equations need but neither use nor find in the data, each with
    the sentence that says what is assumed instead.

    An input counts when the model integrates the state whose equation it enters (P_m: omega,
    v_f: e_qp), does not take it as an argument and the data lack it: the equation then holds
    it constant (a built-in model folds it into a fitted offset).
    """
    terms = {
        t: set(eq.terms) if eq.opaque is None else set()
        for t, eq in zip(model.targets, parse_equations(model.source), strict=True)
    }
    out = {}
    for name, (state, what, _) in _INPUTS.items():
        if state not in model.targets or name in model.arguments or name in channels:
            continue
        how = (
            f"fitted as an offset in d{state}/dt"
            if "1" in terms[state]
            else f"d{state}/dt has no term for it"
        )
        out[name] = f"{name} ({what}) is not measured: assumed constant ({how})"
    return out


def input_caveat(state: str | None, unmeasured: Sequence[str]) -> str:
    """What a term found in d<state>/dt may be when an input of that equation is not measured."""
    names = [n for n in unmeasured if _INPUTS[n][0] == state]
    return "; ".join(
        f"{n} is not measured and assumed constant: the term found may stand in for its "
        f"variation (measure {n} or give {_INPUTS[n][2]})"
        for n in names
    )


def _literal(node: ast.expr, name: str, path: str) -> Any:
    try:
        return ast.literal_eval(node)
    except (ValueError, TypeError, SyntaxError, MemoryError, RecursionError):
        raise ValueError(
            f"{path}: {name} must be a literal list, got {ast.unparse(node)[:80]}"
        ) from None


def parse_model(text: str, name: str = "model", states: Sequence[str] = ()) -> UserModel:
    """A model from a file's text, without executing it.

    The text holds one skeleton function (checked like any skeleton: :mod:`jaxdmd.skeleton`) and
    optionally, at module level, ``PARAMS = [...]`` (or ``DE_PARAMS``, as ``jaxdmd.run`` writes
    ``model.py``) and ``TARGETS = [...]`` (or ``DE_TARGETS``): the states whose derivatives the
    function returns, in order. Without ``TARGETS``, the function's arguments that are in
    ``states`` (the data's state channels), in the data's order, must match its outputs.
    """
    try:
        tree = ast.parse(text)
    except SyntaxError as err:
        raise ValueError(f"{name}: not Python ({err.msg}, line {err.lineno})") from None
    values: dict[str, Any] = {}
    for node in tree.body:
        if isinstance(node, ast.Assign) and len(node.targets) == 1:
            target = node.targets[0]
            if isinstance(target, ast.Name) and target.id in (
                "PARAMS", "DE_PARAMS", "TARGETS", "DE_TARGETS"
            ):  # fmt: skip
                values[target.id] = _literal(node.value, target.id, name)
    functions = [n.name for n in tree.body if isinstance(n, ast.FunctionDef)]
    if not functions:
        raise ValueError(f"{name}: no function found (a skeleton `def f(x, ..., p): ...`)")
    fname = "equation" if "equation" in functions else functions[0]
    try:
        source, _ = extract(text, function_name=fname)
        fdef = ast.parse(source).body[0]
        assert isinstance(fdef, ast.FunctionDef)
        arguments = tuple(a.arg for a in fdef.args.args[:-1])
        targets = values.get("TARGETS", values.get("DE_TARGETS"))
        if targets is None:
            targets = [s for s in states if s in arguments]
            # a state equation need not use its own state (d delta/dt = f(omega)): take the
            # data's states in order, as many as the function returns
            last = fdef.body[-1]
            n_out = (
                len(last.value.elts)
                if isinstance(last, ast.Return) and isinstance(last.value, ast.Tuple)
                else 1
            )
            if n_out != len(targets):
                targets = list(states)[:n_out]
        if not isinstance(targets, list | tuple) or not all(isinstance(t, str) for t in targets):
            raise ValueError(f"{name}: TARGETS must be a list of state names")
        skeleton = compile_skeleton(source, variables=arguments, n_outputs=len(targets))
    except SkeletonError as err:
        raise ValueError(f"{name}: the model does not pass the skeleton check: {err}") from None
    params = values.get("PARAMS", values.get("DE_PARAMS"))
    if params is not None:
        if not isinstance(params, list | tuple) or not all(
            isinstance(v, int | float) and np.isfinite(v) for v in params
        ):
            raise ValueError(f"{name}: PARAMS must be a list of finite numbers")
        if len(params) < skeleton.n_params:
            raise ValueError(
                f"{name}: the function uses {skeleton.n_params} parameters, PARAMS has "
                f"{len(params)}"
            )
        params = tuple(float(v) for v in params)
    return UserModel(name=name, source=skeleton.source, targets=tuple(targets), params=params)


def is_model_file(spec: str) -> bool:
    """Whether ``--model`` names a model file (a ``.py`` path, or any existing file) rather
    than a built-in model."""
    path = Path(spec)
    return path.suffix == ".py" or path.exists()


def load_model(spec: str, states: Sequence[str] = (), channels: Sequence[str] = ()) -> UserModel:
    """A built-in model by name (`builtin_model`), or a model file (see `parse_model`).

    ``states``: the data's state channels; ``channels``: all of the data's channel names."""
    path = Path(spec)
    if is_model_file(spec):
        try:
            text = path.read_text()
        except OSError as err:
            raise ValueError(f"cannot read the model file {spec}: {err.strerror}") from None
        return parse_model(text, name=path.name, states=states)
    return builtin_model(spec, channels)


# ------------------------------------------------------------------------------------------------
# results
# ------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Candidate:
    """A term that would explain part of an equation's residual, with its out-of-sample share."""

    equation: str  # the state whose derivative the equation gives
    term: str  # the term as code, e.g. "(omega - 1)" or "P_m"
    variables: tuple[str, ...]  # channels the term uses
    new_variables: tuple[str, ...]  # those the model does not use
    explained: float  # share of the held-out residual it removes (0..1)
    offset: bool = False  # it needs an offset the model lacks (counted in ``explained``)

    def to_dict(self) -> dict[str, Any]:
        return {
            "equation": self.equation,
            "term": self.term,
            "variables": list(self.variables),
            "new_variables": list(self.new_variables),
            "explained": self.explained,
            "with_offset": self.offset,
        }


@dataclass(frozen=True)
class Cause:
    """The named cause: ``kind`` is ``missing variable``, ``missing term``, ``parameter`` or
    ``none`` (the model agrees with the data within what can be told from them)."""

    kind: str
    summary: str
    equation: str | None = None
    term: str | None = None
    variables: tuple[str, ...] = ()
    explained: float = 0.0
    # the term may stand in for an unmeasured input of its equation (also in ``summary``)
    caveat: str = ""

    def to_dict(self) -> dict[str, Any]:
        return {
            "kind": self.kind,
            "equation": self.equation,
            "term": self.term,
            "variables": list(self.variables),
            "explained": self.explained,
            "summary": self.summary,
            "caveat": self.caveat or None,
        }


@dataclass(frozen=True)
class DiagnoseConfig:
    """Settings of `diagnose`.

    ``threshold``: the out-of-sample share of an equation's residual one term must explain for
    the diagnosis to call the model structurally wrong. ``parameter_gain``: the factor by which
    refitting the given parameters must cut the held-out error to call it a parameter error.
    ``rounds``: round limit of the extension search (``0``: no extension). ``window``: the
    equations are compared with the data in their integral form over windows of this many
    seconds (:func:`jaxdmd.problems.integral_operator`); None compares derivatives (then the
    recordings need derivatives, estimated or given).
    """

    threshold: float = 0.2
    parameter_gain: float = 2.0
    rounds: int = 8
    window: float | None = 3.0  # s, integral form of the equations; None: derivatives
    folds: int = 4  # time blocks for cross-validation when there is a single training recording
    top: int = 8  # candidates kept per equation in the report
    search: SearchConfig = field(
        default_factory=lambda: SearchConfig(n_islands=4, prompts_per_round=4, patience=2)
    )


@dataclass(frozen=True)
class Diagnosis:
    """Everything the report shows; `to_dict` is ``diagnosis.json``."""

    model: UserModel
    cause: Cause
    also: tuple[Candidate, ...]  # other equations whose residual a term explains (> threshold)
    candidates: dict[str, tuple[Candidate, ...]]  # equation -> best terms, best first
    nmse: dict[str, dict[str, float]]  # "given" / "refit" / "extended" -> equation -> NMSE
    metrics: dict[str, dict[str, Any]]  # "given" / "refit" / "extended" -> held-out metrics
    errors: dict[str, dict[str, Any]]  # state -> where and when the model is wrong (`errors_of`)
    given: Equations | None
    refit: Equations
    extended: Equations | None
    coefficients: dict[str, dict[str, float]]  # extended: equation -> term -> value
    held_out: str  # what the held-out data are
    rollouts: dict[str, list[RolloutResult]] = field(repr=False, default_factory=dict)
    test: tuple[Dataset, ...] = field(repr=False, default=())
    extension_rounds: int = 0
    joined: tuple[str, ...] = ()
    wall_time_s: float = 0.0
    window: float | None = None  # s, the integral form's window (None: derivatives)
    # inputs the model needs that the data lack, and what is assumed instead (sentences)
    unmeasured: tuple[str, ...] = ()
    assumptions: tuple[str, ...] = ()
    # the training data the refitted and extended models were fitted to (their standard errors)
    problem: Problem | None = field(repr=False, default=None, compare=False)

    @property
    def errors_of(self) -> str:
        """Which model `errors` were measured on: ``given`` (its own parameters) or ``refit``."""
        return "given" if self.given is not None else "refit"

    @property
    def gain(self) -> float:
        """Held-out error (mean NRMSE over the model's states) before / after the extension."""
        before = self.metrics.get("given", self.metrics["refit"])["nrmse"]
        after = self.metrics.get("extended", self.metrics["refit"])["nrmse"]
        return float(before / after) if after > 0 else float("inf")

    def physical(self) -> dict[str, Any]:
        """The physical parameters of each model (``given``, ``refit``, ``extended``:
        :func:`jaxdmd.physical.physical_parameters` of its state equations); a model that cannot
        be read is left out.

        The refitted and extended models' parameters carry standard errors from the fit that
        produced them: the training `problem` (integral or derivative form), with the errors
        correlated over its overlapping windows. The given model's have
        none: its values were not estimated from these data, and the uncertainty the data leave
        for its structure is the refitted model's."""
        from jaxdmd.physical import physical_parameters

        out: dict[str, Any] = {}
        for name, e in (("given", self.given), ("refit", self.refit), ("extended", self.extended)):
            if e is None:
                continue
            problem = None if name == "given" else self.problem
            for data in (problem, None) if problem is not None else (None,):  # errors may fail
                try:
                    out[name] = physical_parameters(e, None, data)
                    break
                except Exception:  # a report must not fail on the mapping
                    continue
        return out

    def to_dict(self) -> dict[str, Any]:
        def eq(e: Equations | None) -> dict[str, Any] | None:
            if e is None:
                return None
            return {
                "source": e.source,
                "params": list(e.params),
                "equations": e.readable(),
                "nmse": dict(zip(e.contract.targets, e.losses, strict=True)),
            }

        return {
            "model": {
                "name": self.model.name,
                "targets": list(self.model.targets),
                "params_given": self.model.params is not None,
            },
            "unmeasured": list(self.unmeasured),
            "assumptions": list(self.assumptions),
            "cause": self.cause.to_dict(),
            "also": [c.to_dict() for c in self.also],
            "candidates": {k: [c.to_dict() for c in v] for k, v in self.candidates.items()},
            "errors": self.errors,
            "errors_of": self.errors_of,
            "nmse": self.nmse,
            "metrics": self.metrics,
            "gain": self.gain,
            "held_out": self.held_out,
            "models": {
                "given": eq(self.given),
                "refit": eq(self.refit),
                "extended": eq(self.extended),
            },
            "coefficients": self.coefficients,
            "physical_parameters": {k: r.to_dict() for k, r in self.physical().items()},
            "extension": {"rounds": self.extension_rounds, "joined": list(self.joined)},
            "wall_time_s": self.wall_time_s,
            "window_s": self.window,
        }


# ------------------------------------------------------------------------------------------------
# the steps
# ------------------------------------------------------------------------------------------------


def split_held_out(
    train: Sequence[Dataset], test: Sequence[Dataset] | None, share: float = 0.3
) -> tuple[list[Dataset], list[Dataset], str]:
    """Training and held-out recordings, and how the held-out ones were chosen.

    Given test recordings are the held-out data. Otherwise, with several training recordings the
    last one is held out; with one, its last ``share`` of time (the model is simulated from the
    measured state at the start of that window).
    """
    train = list(train)
    if not train:
        raise ValueError("no training recordings")
    if test:
        return train, list(test), f"{len(test)} separate recording(s)"
    if len(train) > 1:
        return train[:-1], train[-1:], "the last training recording (left out of the fit)"
    ds = train[0]
    t = np.asarray(ds.t)
    cut = float(t[0] + (1 - share) * (t[-1] - t[0]))
    cut = float(t[np.searchsorted(t, cut)])
    fit_part, held = ds.window(float(t[0]), cut), ds.window(cut, float(t[-1]))
    return (
        [fit_part],
        [held],
        f"the last {share:.0%} of the recording (t >= {cut:g} s; the fit uses t <= {cut:g} s)",
    )


def _block_groups(datasets: Sequence[Dataset], folds: int) -> np.ndarray | None:
    if len(datasets) > 1:
        return None
    n = datasets[0].n_samples
    return np.minimum(np.arange(n) * folds // n, folds - 1)


def _cv_nmse(x: np.ndarray, y: np.ndarray, groups: np.ndarray) -> float:
    """Leave-one-group-out least-squares NMSE (held-out squared errors over the variance)."""
    sse = 0.0
    for g in np.unique(groups):
        held = groups == g
        if x.shape[1]:
            coef, *_ = np.linalg.lstsq(x[~held], y[~held], rcond=None)
            r = y[held] - x[held] @ coef
        else:
            r = y[held]
        sse += float(r @ r)
    return sse / (len(y) * (float(np.var(y)) or 1.0))


def _term_variables(term: str) -> tuple[str, ...]:
    names = {n.id for n in ast.walk(ast.parse(term, mode="eval")) if isinstance(n, ast.Name)}
    return tuple(sorted(names - {"jnp", "np"}))


def rank_terms(
    problem: Problem, model: UserModel, refit_params: Sequence[float], top: int = 8
) -> dict[str, tuple[Candidate, ...]]:
    """For each equation, the grammar's terms ranked by the share of the held-out residual each
    removes when added to the model's equation.

    ``problem`` is best in the integral form (``de_problem(..., integral=...)``): increments of
    the states over windows against the integrals of the terms. Integration averages the noise
    of the states out, so a slow, small bias (a missing saturation, say) that a simulation
    integrates into a large error is seen as such. Each candidate is fitted together with the
    model's own terms (and with an offset if the model has none) by least squares with one
    recording (or time block) left out at a time; its share is ``1 - CV error with it / CV
    error without it``.
    """
    offline = OfflineProposer.for_problem(problem)
    if offline.groups is None:
        raise ValueError("ranking needs at least two recordings or time blocks (groups)")
    groups = offline.groups
    pool = term_pool([*_variables_of(problem)], offline.data)
    skeleton = model.skeleton()
    equations = parse_equations(model.source)
    used = set(model.arguments)
    full = {k: jnp.asarray(v) for k, v in problem.variables.items() if k in skeleton.arguments}
    pred = np.asarray(skeleton(full, jnp.asarray(refit_params)))
    out: dict[str, tuple[Candidate, ...]] = {}
    for j, target in enumerate(model.targets):
        y = offline.targets[j]
        if equations[j].opaque is None:
            base = offline.design(equations[j].terms)
            present = set(equations[j].terms)
        else:  # not affine in p: the fitted equation stands for it
            column = pred[j]
            if problem.operator is not None:
                column = np.asarray(problem.operator(jnp.asarray(column)))
            base = column[offline.index][:, None]
            present = set()
        before = _cv_nmse(base, y, groups)
        offset = None if "1" in present else offline.column("1")
        rows = []
        for term in pool:
            col = offline.column(term)
            if term in present or col is None:
                continue
            after = _cv_nmse(np.column_stack([base, col]), y, groups)
            with_offset = False
            if offset is not None and term != "1":  # f(x) - f(x0) needs an offset
                both = _cv_nmse(np.column_stack([base, col, offset]), y, groups)
                # the offset must earn its place as any term would (2 % of the CV error)
                with_offset = both < 0.98 * after
                after = min(after, both)
            share = 1.0 - after / before if before > 0 else 0.0
            names = _term_variables(term)
            rows.append(
                Candidate(
                    equation=target,
                    term=term,
                    variables=names,
                    new_variables=tuple(n for n in names if n not in used),
                    explained=float(share),
                    offset=with_offset,
                )
            )
        rows.sort(key=lambda c: (-c.explained, len(c.variables), len(c.term)))
        out[target] = tuple(rows[:top])
    return out


def _variables_of(problem: Problem):
    from jaxdmd.prompts import Variable

    seen = {v.name for v in problem.catalog}
    extra = [Variable(n, "state") for n in problem.target_names if n not in seen]
    return (*extra, *problem.catalog)


def _simplest(candidates: Sequence[Candidate], tolerance: float = 0.05) -> Candidate:
    """The simplest of the terms that tie with the best one.

    A tie: the held-out error left with the term is within ``tolerance`` (relative) of the error
    left with the best term (the parsimony rule of :func:`jaxdmd.search.final_equations`). Among
    ties, the term that needs no new measurement wins, then the one with fewer factors (a scaled
    copy ``x * c`` of a term ``x`` with a nearly constant ``c`` ties with ``x``), then the better.
    """
    left = 1.0 - candidates[0].explained
    ties = [c for c in candidates if 1.0 - c.explained <= left * (1 + tolerance)]
    return min(ties, key=lambda c: (len(c.new_variables), c.term.count(" * "), -c.explained))


def locate_errors(sim: RolloutResult, meas: Dataset, states: Sequence[str]) -> dict[str, Any]:
    """Where and when a simulation departs from a recording, per state (RMS error / range)."""
    t = np.asarray(meas.t)
    window = fault_window(meas)
    phases: dict[str, np.ndarray] = {"whole": np.ones_like(t, dtype=bool)}
    if window is not None:
        phases["before fault"] = t < window[0]
        phases["fault window"] = (t >= window[0]) & (t <= window[1])
        phases["after fault"] = t > window[1]
    out = {}
    for s in states:
        x = np.asarray(meas[s], dtype=float)
        e = np.asarray(sim[s], dtype=float) - x
        scale = float(np.ptp(x)) or float(np.max(np.abs(x))) or 1.0
        row: dict[str, Any] = {}
        for name, mask in phases.items():
            row[name] = float(np.sqrt(np.mean(e[mask] ** 2)) / scale) if mask.any() else None
        late = phases.get("after fault", np.ones_like(t, dtype=bool)) & np.isfinite(e)
        drift = False
        if late.sum() > 10:
            slope, icpt = np.polyfit(t[late], e[late], 1)
            trend = slope * t[late] + icpt
            total = float(np.sum(e[late] ** 2)) or 1e-300
            drift = (
                float(np.sum(trend**2)) / total > 0.5
                and abs(slope) * np.ptp(t[late]) > 0.05 * scale
            )
        row["drift"] = bool(drift)
        finite = {k: v for k, v in row.items() if k not in ("whole", "drift") and v is not None}
        row["worst"] = max(finite, key=lambda k: finite[k]) if finite else "whole"
        row["diverged_at"] = sim.diverged_at
        out[s] = row
    return out


def coefficients(eq: Equations) -> dict[str, dict[str, float]]:
    """Each equation's fitted coefficient per term (affine equations; others are skipped)."""
    lines, mappings = ln.split_lines(eq.source)
    out: dict[str, dict[str, float]] = {}
    for target, line, mapping in zip(eq.contract.targets, lines, mappings, strict=True):
        source = ln.assemble("f", [*line.variables()], [line], ["y"])
        (parsed,) = parse_equations(source)
        if parsed.opaque is not None:
            continue
        rendered = parsed.render()
        # refit-free: evaluate the line's coefficient of each term from its parameters
        params = [eq.params[i] for i in mapping]
        if rendered.text != ln.split_lines(source)[0][0].text:
            continue  # the line repeats a term or scales it: no one coefficient per term
        out[target] = {term: float(v) for term, v in zip(parsed.terms, params, strict=True)}
    return out


def _fitted(state: SearchState) -> Equations:
    top = state.archive.islands[0].entries[0]
    return Equations(state.contract, top.source, top.params, top.losses, top.score)


def _nmse(problem: Problem, model: UserModel, params: Sequence[float]) -> dict[str, float]:
    skeleton = model.skeleton()
    data = {k: problem.variables[k] for k in skeleton.arguments}
    pred = skeleton(data, jnp.asarray(params))
    if problem.operator is not None:
        pred = jax.vmap(problem.operator)(pred)
    target = problem.targets
    err = jnp.mean((pred - target) ** 2, axis=1) / jnp.var(target, axis=1)
    return {t: float(v) for t, v in zip(model.targets, err, strict=True)}


def _held_out_metrics(
    block: Block, test: Sequence[Dataset]
) -> tuple[dict[str, Any], list[RolloutResult]]:
    sims = [rollout(block, ds, mode="de") for ds in test]
    per = [metrics(sim, ds, block.targets) for sim, ds in zip(sims, test, strict=True)]
    states = {
        s: {k: float(np.mean([m["per_state"][s][k] for m in per])) for k in ("nrmse", "r2", "mape")}
        for s in block.targets
    }
    mean = {k: float(np.mean([m["mean"][k] for m in per])) for k in ("nrmse", "r2", "mape")}
    return {**mean, "per_state": states, "diverged": any(s.diverged for s in sims)}, sims


def _check_data(model: UserModel, datasets: Sequence[Dataset]) -> None:
    first = datasets[0]
    missing = [n for n in (*model.targets, *model.arguments) if n not in first]
    if missing:
        raise ValueError(
            f"the data lack the channels the model {model.name!r} needs: {', '.join(missing)} "
            f"(the data have {', '.join(first.names)})"
        )
    not_states = [n for n in model.targets if first.role(n) != "state"]
    if not_states:
        raise ValueError(
            f"the model integrates {', '.join(not_states)}, which the data do not mark as "
            "states (role 'state')"
        )


def _cause(
    ranking: dict[str, tuple[Candidate, ...]],
    flagged: Sequence[Candidate],
    held_metrics: dict[str, dict[str, Any]],
    nmse: dict[str, dict[str, float]],
    config: DiagnoseConfig,
    unmeasured: Sequence[str] = (),
) -> Cause:
    """The verdict: a structural cause if a term explains enough, else parameters, else none.

    A term found in an equation that an unmeasured input enters (``unmeasured``) is named with
    the caveat that it may stand in for that input's variation."""
    if flagged:
        eq_name = flagged[0].equation
        pick = _simplest([c for c in ranking[eq_name] if c.explained > 0])
        what = f"variable {', '.join(pick.new_variables)}" if pick.new_variables else "a term"
        caveat = input_caveat(eq_name, unmeasured)
        return Cause(
            kind="missing variable" if pick.new_variables else "missing term",
            summary=(
                f"the d{eq_name}/dt equation lacks {what}: adding {pick.term}"
                f"{' with an offset' if pick.offset else ''} removes "
                f"{pick.explained:.0%} of its residual on data it was not fitted to"
                + (f". Caveat: {caveat}" if caveat else "")
            ),
            equation=eq_name,
            term=pick.term,
            variables=pick.new_variables or pick.variables,
            explained=pick.explained,
            caveat=caveat,
        )
    before, refit = held_metrics.get("given"), held_metrics["refit"]
    if before is not None and before["nrmse"] > config.parameter_gain * refit["nrmse"]:
        ratio = before["nrmse"] / max(refit["nrmse"], 1e-300)
        worst = max(nmse["refit"], key=lambda s: nmse["given"][s] / max(nmse["refit"][s], 1e-300))
        return Cause(
            kind="parameter",
            summary=(
                f"the structure fits: refitting the parameters alone cuts the held-out error "
                f"{ratio:.1f}x (most in the d{worst}/dt equation), and no term explains "
                f"{config.threshold:.0%} of what is left"
            ),
            equation=worst,
        )
    return Cause(
        kind="none",
        summary=(
            f"no term explains {config.threshold:.0%} of any equation's residual out of "
            "sample; the model agrees with the data as far as they can tell"
        ),
    )


def diagnose(
    train: Sequence[Dataset],
    model: UserModel,
    *,
    test: Sequence[Dataset] | None = None,
    key: jax.Array | None = None,
    config: DiagnoseConfig | None = None,
    matched: bool = True,
    on_round: Callable[[SearchState, search.RoundReport], None] | None = None,
) -> Diagnosis:
    """Diagnose ``model`` on the recordings (see the module docstring).

    Args:
        train: recordings the model is fitted and extended on. With ``matched`` their
            derivatives must be the default estimates (``with_estimated_derivatives()``).
        model: the model under test (`load_model`, `builtin_model`, `parse_model`).
        test: held-out recordings; without them, see `split_held_out`.
        key: PRNG key of the extension search.
        config: `DiagnoseConfig`.
        matched: fit predictions smoothed like the derivative estimates (see
            :func:`jaxdmd.problems.de_problem`); False for exact, given derivatives.
        on_round: progress callback of the extension search.
    """
    start = time.perf_counter()
    config = config or DiagnoseConfig()
    key = jax.random.key(0) if key is None else key
    train, held, held_text = split_held_out(train, test)
    _check_data(model, [*train, *held])
    assumed = unmeasured_inputs(model, train[0].names)
    states = model.targets
    library = [a for a in model.arguments if a not in states]
    problem, contract = de_problem(
        train,
        matched=matched and config.window is None,
        states=states,
        library=library,
        groups=_block_groups(train, config.folds),
        integral=config.window,
    )
    cfg = config.search if config.rounds == 0 else _with_rounds(config.search, config.rounds)
    k_init, k_search = jax.random.split(key)
    state = search.init(problem, contract, k_init, cfg, seed=model.source)
    refit = _fitted(state)
    nmse = {"refit": _nmse(problem, model, refit.params)}
    given = None
    if model.params is not None:
        params = tuple(model.params[: model.skeleton().n_params])
        nmse["given"] = _nmse(problem, model, params)
        losses = tuple(nmse["given"][t] for t in contract.targets)
        given = Equations(contract, refit.source, params, losses, -float(np.mean(losses)))

    # 1. what the simulation gets wrong
    runs: dict[str, list[RolloutResult]] = {}
    held_metrics: dict[str, dict[str, Any]] = {}
    for name, eq in (("given", given), ("refit", refit)):
        if eq is not None:
            held_metrics[name], runs[name] = _held_out_metrics(as_block(eq), held)
    errors = locate_errors(runs["given" if given is not None else "refit"][0], held[0], states)

    # 2.-3. the cause
    ranking = rank_terms(problem, model, refit.params, top=max(config.top, 1))
    flagged = sorted(
        (c for cands in ranking.values() for c in cands[:1] if c.explained >= config.threshold),
        key=lambda c: -c.explained,
    )
    cause = _cause(ranking, flagged, held_metrics, nmse, config, tuple(assumed))
    also = tuple(c for c in flagged if c.equation != cause.equation)

    # 4. the extension
    extended = None
    coefs: dict[str, dict[str, float]] = {}
    rounds = 0
    joined: tuple[str, ...] = ()
    if cause.kind in ("missing variable", "missing term") and config.rounds > 0:
        state, suggestions = _offer(state, model, ranking, flagged, cause)
        state = search.replace_state(state, key=k_search)
        proposer = _WithSuggestions(OfflineProposer.for_problem(state.problem), suggestions)
        state = run_loop(state, proposer, on_round=on_round)
        extended = _keep_unflagged(
            # no absolute floor: NMSEs of the integral form are far below the derivatives'
            search.final_equations(state, floor=0.0),
            refit,
            {c.equation for c in flagged},
            state,
        )
        coefs = coefficients(extended)
        rounds = state.iteration
        joined = tuple(v.name for v in state.contract.library if v.name not in model.arguments)
        held_metrics["extended"], runs["extended"] = _held_out_metrics(as_block(extended), held)
        nmse["extended"] = dict(zip(extended.contract.targets, extended.losses, strict=True))
    return Diagnosis(
        model=model,
        cause=cause,
        also=also,
        candidates=ranking,
        nmse=nmse,
        metrics=held_metrics,
        errors=errors,
        given=given,
        refit=refit,
        extended=extended,
        coefficients=coefs,
        held_out=held_text,
        rollouts=runs,
        test=tuple(held),
        extension_rounds=rounds,
        joined=joined,
        wall_time_s=time.perf_counter() - start,
        window=config.window,
        problem=problem,
        unmeasured=tuple(assumed),
        assumptions=tuple(assumed.values()),
    )


@dataclass
class _WithSuggestions:
    """The offline proposer, its first round topped up with the diagnosis's suggestions."""

    inner: OfflineProposer
    suggestions: list[str]

    def propose(self, requests: Sequence[Any]) -> list[Sample]:
        extra, self.suggestions = self.suggestions, []
        samples = list(self.inner.propose(requests))
        return samples + [Sample(text=text, island=0, origin="diagnosis") for text in extra]


def _keep_unflagged(
    found: Equations, refit: Equations, flagged: set[str], state: SearchState
) -> Equations:
    """The extension changes only the flagged equations: the others keep the model's own lines
    (refitted), so that nothing the data do not ask for is changed."""
    targets = found.contract.targets
    new_lines, _ = ln.split_lines(found.source)
    old_lines, _ = ln.split_lines(refit.source)
    lines = [
        new if t in flagged else old
        for t, new, old in zip(targets, new_lines, old_lines, strict=True)
    ]
    if all(a.text == b.text for a, b in zip(lines, new_lines, strict=True)):
        return found
    source = ln.assemble(
        found.contract.function_name, found.contract.arguments, lines, found.contract.outputs
    )
    skeleton = search._compile(source, found.contract)
    (result,) = search.fit_problem(
        [skeleton], state.problem, jax.random.fold_in(state.key, 11), state.config.fit
    )
    if result.error is not None:
        return found
    return Equations(
        found.contract,
        skeleton.source,
        tuple(float(x) for x in result.params),
        tuple(float(x) for x in result.losses),
        float(result.score),
    )


def _with_rounds(config: SearchConfig, rounds: int) -> SearchConfig:
    from dataclasses import replace

    return replace(config, max_rounds=rounds)


def _offer(
    state: SearchState,
    model: UserModel,
    ranking: dict[str, tuple[Candidate, ...]],
    flagged: Sequence[Candidate],
    cause: Cause,
) -> tuple[SearchState, list[str]]:
    """Bring the named variables into the library; the model plus the best terms as samples."""
    from jaxdmd.prompts import Contract

    new = []
    for c in flagged:
        for v in c.new_variables:
            if v not in new:
                new.append(v)
    contract = state.contract
    if new:
        library = (*contract.library, *(state.problem.find(v) for v in new))
        contract = Contract(
            loop=contract.loop,
            targets=contract.targets,
            states=contract.states,
            library=tuple(v for v in library if v is not None),
            function_name=contract.function_name,
            system=contract.system,
        )
        state = search.replace_state(
            state,
            contract=contract,
            joined=(*state.joined, *((v, 0) for v in new)),
        )
    lines, _ = ln.split_lines(model.source)
    suggestions = []
    named = [(cause.equation, cause.term)]
    for picks in (named, [*named, *((c.equation, c.term) for c in flagged)]):
        new_lines = list(lines)
        for j, target in enumerate(model.targets):
            chosen = [c for c in ranking[target] if (target, c.term) in picks]
            terms = [c.term for c in chosen]
            if any(c.offset for c in chosen):
                terms.append("1")
            if not terms:
                continue
            line = new_lines[j]
            extra = " + ".join(
                f"p[{line.n_params + i}]" + ("" if t == "1" else f" * {wrap(t)}")
                for i, t in enumerate(terms)
            )
            expr = ast.parse(f"{line.text} + {extra}", mode="eval").body
            new_lines[j] = ln.Line(expr, line.n_params + len(terms))
        suggestions.append(
            ln.assemble(contract.function_name, contract.arguments, new_lines, contract.outputs)
        )
    return state, list(dict.fromkeys(suggestions))
