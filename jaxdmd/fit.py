"""Batched fitting of candidate skeletons: all candidates of a round, all restarts, one compile.

A round of the search produces a handful of candidate skeletons (``jaxdmd.skeleton.Skeleton``),
each a pure JAX function ``fn(*variables, p) -> tuple of n_outputs arrays`` with a trainable
parameter vector ``p``. :func:`fit_batch` fits every candidate, from several random starting
points each, and returns one :class:`FitResult` per candidate. Nothing is compiled per
candidate: the skeletons are lowered to register-machine programs, and the least-squares loop
runs them on the host (default) or in one jitted interpreter compiled once per process.

Score
-----
For a candidate with predictions ``pred[k, n]`` of the targets ``target[k, n]`` (output ``k``,
sample ``n``) and non-negative sample weights ``w[k, n]`` (default 1)::

    losses[k] = NMSE_k = mean_n( w[k, n] * (pred[k, n] - target[k, n])**2 ) / var_n(target[k])
    score     = -mean_k(losses[k])                     (-inf if the candidate was dropped)

The variance is the plain (unweighted) variance of the target over all samples; a constant
target (variance 0) is normalised by 1 instead. Weights are used as given: weights with mean 1
keep NMSE on its usual scale (a model that predicts the mean scores about 1, a perfect one 0).
Normalising by the variance makes scores comparable across equations and data sets. The losses
are kept per output because the state equations are separable: the search keeps the best
equation for each state.

Algorithm (measured against the alternatives in ``benchmarks/fit_speed.py``; see docs/fit.md)
-----------------------------------------------------------------------------------------------
XLA compilation, not arithmetic, is the cost of fitting small models on a CPU. The fit is
therefore a second-order method (few iterations) that needs no compile per candidate:

1. *Restarts.* Restart 0 starts from ``p = 1`` (the LLM-SR convention); restart ``i > 0`` from
   ``p_j = s_j * 10**u_j`` with random sign ``s_j`` and ``u_j ~ U(-init_log10_range,
   init_log10_range)``: magnitudes from 0.1 to 10 by default, spread evenly in log scale. The
   draws of a candidate depend only on the key and the candidate's source text, so a candidate
   gets the same fit whatever else is in the batch.
2. *Optional Adam* (``adam_steps > 0``, off by default): the paper's Adam with a cosine-annealed
   learning rate (optax) on the summed NMSE. Measured: it costs compile and run time and does not
   improve on step 3, whose damping is scale invariant (coefficients range from 0.01 to 377).
3. *Levenberg-Marquardt polish*, written here (in NumPy in :mod:`jaxdmd.lm` for the default
   host backend, in a few lines of JAX below): Jacobian by forward mode
   (the interpreter's, or ``jvp`` vmapped over the parameter basis), normal equations
   ``(J^T J + lambda D) dp = -J^T r``
   with Marquardt scaling ``D = diag(J^T J)``, one batched Cholesky solve for all candidates and
   restarts (parameters padded to the largest candidate), inside a ``lax.while_loop`` that stops
   when every fit has converged (``ftol`` on accepted steps, ``xtol`` on the step tried, or the
   damping reaching ``max_damping``). For a skeleton linear in ``p`` the first step is the exact
   least-squares solution. The equations are separable, so LM runs per *output component*: the
   outputs are grouped by shared parameters (from the Jacobian's sparsity, found at run time),
   and every group has its own damping, acceptance and convergence test, as if each equation were
   fitted alone. An equation that is hard to fit does not slow the others down.
4. *Per-equation restart selection* (on the host, from the returned arrays). For each group of
   outputs the best restart is kept and the groups' parameters are combined; the losses of a
   group depend only on its own parameters, so the combined losses are exact. Eight restarts of
   a five-equation candidate thus act as eight restarts per equation, not eight joint draws.

How the candidates are run (``FitConfig.interpreter`` and ``backend``)
-------------------------------------------------------------------
0. *Exact least squares first* (``linear_shortcut``). A candidate affine in ``p`` is solved
   exactly on the host; so is every *group of outputs* of a nonlinear candidate that is affine in
   its own parameters (outputs sharing no parameter are separate problems). Only the nonlinear
   groups go to Levenberg-Marquardt.
1. *One interpreter for every candidate.* A skeleton made by ``jaxdmd.skeleton.compile_skeleton``
   is lowered to register-machine programs (:mod:`jaxdmd.interp`): its parameter-free
   subexpressions become host-side feature rows (computed once, in NumPy), and each output gets
   its own short program whose Jacobian is only as wide as that output's parameters.
   *Host backend* (``FitConfig.backend="host"``, the default): :mod:`jaxdmd.lm` runs the same LM
   per output group in NumPy (:func:`jaxdmd.interp.run_numpy`, the interpreter's NumPy twin with
   the same derivative rules). Nothing is traced or compiled, so the first round of a process
   costs what every later round costs; a trial point's Jacobian is computed only if the step is
   accepted, and stopped restarts leave the arrays (measured in docs/fit.md: a round of 16
   candidates in 0.3-0.5 s, against 2.5 s for the jitted interpreter's first round).
   *XLA backend* (``backend="xla"``, and whenever ``adam_steps > 0``): one jitted
   fit (this LM loop around a ``lax.map`` over (candidate, output) slots, a ``lax.switch``
   interpreter with hand-written forward-mode derivatives, restarts as an array dimension) runs
   any batch: programs are data, shapes are padded to buckets (8 candidates per call; parameters,
   registers and feature rows to powers of two), so the executable is compiled once per process
   and reused in every round. A slot whose output group has converged at every restart is skipped.
   With JAX's persistent compilation cache configured (``jax_compilation_cache_dir``), the
   compiled executable and (with the optional ``flatbuffers``) the traced function are kept on
   disk, so a later process neither traces nor compiles it.
2. *Fallback.* Skeletons without a program (a ``fn`` not made from its ``source``, or
   ``interpreter=False``) are traced into one fused function (a Python loop over candidates
   inside ``jit``, ``vmap`` over restarts, forward-mode Jacobian by ``jvp``): one XLA compile per
   batch of distinct candidates, which is what the interpreter avoids.

Failures never break a batch: each candidate without a program is first *traced* on its own
(``jax.eval_shape`` of its residual and Jacobian; no XLA compile; a lowered program needs no
trace), and a candidate that fails to trace, reads an unknown
variable, or returns the wrong number or shape of outputs is dropped with the reason. Inside the
fit non-finite values are masked (a non-finite trial step is rejected like a step that increases
the loss); a candidate whose every restart stays non-finite, or whose NMSE exceeds ``max_nmse``,
is returned with ``score = -inf`` and the reason in ``error``. If the interpreter fit raises,
its candidates go through the fallback; if a fused compile fails, the candidates are fitted one
by one so that only the culprit is lost.
"""

from __future__ import annotations

import dataclasses
import functools
import zlib
from collections.abc import Callable, Mapping, Sequence
from typing import Any, Protocol

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax import lax

from jaxdmd import interp, lm

__all__ = ["FitConfig", "FitResult", "Operator", "fit_batch", "nmse"]

Array = jax.Array


class SkeletonLike(Protocol):
    """What :func:`fit_batch` needs of a ``jaxdmd.skeleton.Skeleton``."""

    source: str
    name: str
    arguments: tuple[str, ...]
    n_params: int
    n_outputs: int
    fn: Callable[..., Any]


@dataclasses.dataclass(frozen=True)
class FitConfig:
    """Settings of :func:`fit_batch`.

    Attributes:
        restarts: random starting points per candidate (restart 0 starts from ``p = 1``).
        adam_steps: Adam steps before the LM polish; 0 (the default) skips Adam.
        learning_rate: Adam's peak learning rate (cosine-annealed to 0 over ``adam_steps``).
        polish_steps: maximum Levenberg-Marquardt iterations (the loop stops earlier when every
            fit has converged).
        init_log10_range: restarts draw ``|p_j| = 10**U(-r, r)`` with a random sign.
        first_restart_ones: start restart 0 from ``p = 1``.
        damping: initial LM damping ``lambda`` (relative to ``diag(J^T J)``).
        damping_up: factor on ``lambda`` after a rejected step.
        damping_down: factor on ``lambda`` after an accepted step.
        max_damping: a fit whose ``lambda`` exceeds this is considered converged (stuck).
        ftol: converged when an accepted step lowers the group's loss by less than this fraction.
        xtol: converged when the step just tried (accepted or not) changes every parameter of
            the group by less than this fraction (a stationary point: without it, a converged
            fit spends ~19 rejected steps raising the damping to ``max_damping``). Outputs that
            depend on no parameter are converged from the start.
        max_nmse: a candidate whose mean NMSE exceeds this is dropped as diverged.
        combine_restarts: choose the best restart per group of separable outputs (else the best
            restart of the candidate as a whole).
        linear_shortcut: solve candidates that are affine in ``p`` exactly by weighted linear
            least squares, evaluated eagerly (no XLA compile of the candidate); see
            :func:`_linear_fit`. A lowered candidate is solved a group of outputs (linked by
            shared parameters) at a time, and only its groups that are not affine go through
            Levenberg-Marquardt.
        compiler_options: XLA options for the fused compile, as ``(name, value)`` pairs. The
            default turns XLA:CPU's new fusion emitters off, which roughly halves the compile
            time of these many small fusions at equal run time (measured, docs/fit.md).
        interpreter: run lowered skeletons in the one pre-built interpreter
            (:mod:`jaxdmd.interp`) instead of compiling them; False compiles every batch.
        interpreter_chunk: candidates per interpreter call (a fixed shape: one compile).
        backend: where lowered skeletons are fitted: ``"host"`` (the default) runs the
            Levenberg-Marquardt loop in NumPy on the host (:mod:`jaxdmd.lm`: nothing is
            compiled, so a process's first round costs what its later rounds cost); ``"xla"``
            runs it in the jitted interpreter (compiled once per process). With
            ``adam_steps > 0`` the fit runs in the jitted interpreter whatever this says.
    """

    restarts: int = 8
    adam_steps: int = 0
    learning_rate: float = 1e-2
    polish_steps: int = 50
    init_log10_range: float = 1.0
    first_restart_ones: bool = True
    damping: float = 1e-3
    damping_up: float = 10.0
    damping_down: float = 0.1
    max_damping: float = 1e16
    ftol: float = 1e-8
    xtol: float = 1e-10
    max_nmse: float = 1e6
    combine_restarts: bool = True
    linear_shortcut: bool = True
    compiler_options: tuple[tuple[str, Any], ...] = (("xla_cpu_use_fusion_emitters", False),)
    interpreter: bool = True
    interpreter_chunk: int = 8
    backend: str = "host"


@dataclasses.dataclass(frozen=True)
class FitResult:
    """The fit of one candidate.

    Attributes:
        params: the best parameters, ``[n_params]`` (per output group when outputs are separable).
        losses: per-output NMSE, ``[n_outputs]`` (see the module docstring for the definition).
        score: ``-mean(losses)``; ``-inf`` if the candidate was dropped.
        error: why the candidate was dropped (trace failure, non-finite, diverged), else None.
        restart_losses: per-restart, per-output NMSE after the polish, ``[restarts, n_outputs]``
            (empty if the candidate was dropped before fitting).
    """

    params: np.ndarray
    losses: np.ndarray
    score: float
    error: str | None = None
    restart_losses: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 0)))


def nmse(pred: Any, target: Any, weights: Any | None = None) -> np.ndarray:
    """Per-output NMSE ``mean(w * (pred - target)**2) / var(target)`` (NumPy, for reference)."""
    pred = np.atleast_2d(np.asarray(pred, dtype=np.float64))
    target = np.atleast_2d(np.asarray(target, dtype=np.float64))
    w = np.ones_like(target) if weights is None else np.broadcast_to(weights, target.shape)
    return np.mean(w * (pred - target) ** 2, axis=1) / _variance(target)


def _variance(target: np.ndarray) -> np.ndarray:
    var = np.var(target, axis=1)
    return np.where(var > 0, var, 1.0)


# ---------------------------------------------------------------------------------------------
# One candidate: residuals, losses, Jacobian products


def _on_device(x: Any, dtype: Any = None) -> Array:
    """A host array on the device. ``jax.device_put``, not ``jnp.asarray``: in this JAX the
    latter compiles a small XLA program per new shape (tens of ms each, on every cold start)."""
    return jax.device_put(np.asarray(x, dtype=dtype))


class Operator:
    """A linear operator applied to every prediction before it is compared with the targets.

    ``(S y)_i = sum_k weight[i, k] * y[index[i, k]]`` (a band matrix; see
    :func:`jaxdmd.data.matched_filter`, which makes the operator matched to a derivative
    estimator). Compared by identity, so it can sit in the compiled fit's cache key.

    The indices are 32-bit where the samples allow (below 2**31 of them): the band of a long
    recording is the largest array a fit holds besides the data, and :attr:`band` shares its
    buffers.
    """

    def __init__(self, index: Any, weight: Any):
        index = np.asarray(index)
        small = index.size == 0 or (index.min() >= 0 and index.max() < np.iinfo(np.int32).max)
        self.index = _on_device(index, np.int32 if small else np.int64)
        self.weight = _on_device(weight, np.float64)
        if self.index.shape != self.weight.shape or self.index.ndim != 2:
            raise ValueError("operator index and weight must both be [N, w]")
        self._band: Any = None

    @property
    def band(self) -> Any:
        """The operator as a SciPy CSR matrix (:func:`jaxdmd.lm.band_matrix`), built once and on
        the operator's own buffers (no copy of the indices or weights)."""
        if self._band is None:
            self._band = lm.band_matrix(self.index, self.weight)
        return self._band

    def __getstate__(self) -> dict[str, Any]:
        # the band is rebuilt where it is used: pickled, it would travel (and be held) as a copy
        return {**self.__dict__, "_band": None}

    def __call__(self, y: Array) -> Array:
        return jnp.sum(y[..., self.index] * self.weight, axis=-1)


@dataclasses.dataclass(frozen=True)
class _Model:
    """A checked candidate: its function, arguments, (padded) parameter count and operator."""

    fn: Callable[..., Any]
    arguments: tuple[str, ...]
    n_params: int  # >= 1 (a parameter-free candidate gets one dummy parameter)
    seed: int
    operator: Operator | None = None


def _predict(model: _Model, data: Mapping[str, Array], p: Array, n_outputs: int) -> Array:
    """``[n_outputs, N]`` predictions; scalar (constant) outputs are broadcast."""
    n = next(iter(data.values())).shape[0]
    out = model.fn(*(data[a] for a in model.arguments), p)
    if not isinstance(out, tuple | list):
        out = tuple(out) if getattr(out, "ndim", 0) == 2 else (out,)
    if len(out) != n_outputs:
        raise ValueError(f"returned {len(out)} outputs, expected {n_outputs}")
    rows = []
    for k, o in enumerate(out):
        o = jnp.asarray(o, dtype=jnp.float64)
        if o.size == 1:
            o = jnp.reshape(o, ())
        elif o.shape != (n,):
            raise ValueError(f"output {k} has shape {o.shape}, expected () or ({n},)")
        rows.append(jnp.broadcast_to(o, (n,)))
    pred = jnp.stack(rows)
    return pred if model.operator is None else model.operator(pred)


def _residual(model, data, targets, scale, p):
    """Scaled residuals ``sqrt(w / (N var)) * (pred - target)``: sum of squares = NMSE."""
    return (_predict(model, data, p, targets.shape[0]) - targets) * scale


def _losses(r: Array) -> Array:
    """Per-output NMSE from scaled residuals ``[K, N]``; non-finite -> +inf."""
    loss = jnp.sum(r * r, axis=-1)
    return jnp.where(jnp.isfinite(loss), loss, jnp.inf)


def _linearise(model, data, targets, scale, p):
    """Losses ``[K]``, ``J^T J`` ``[P, P]``, ``J^T r`` ``[P]`` and dependence ``[K, P]`` at p."""
    return _linearise_fn(lambda q: _residual(model, data, targets, scale, q), p)


def _linearise_fn(f: Callable[[Array], Array], p: Array):
    """:func:`_linearise` for any residual function ``f(p) -> [K, N]``."""
    eye = jnp.eye(p.shape[0], dtype=p.dtype)
    r, jac = jax.vmap(lambda v: jax.jvp(f, (p,), (v,)), out_axes=(None, -1))(eye)  # J [K, N, P]
    jac = jnp.where(jnp.isfinite(jac), jac, 0.0)
    rf = jnp.where(jnp.isfinite(r), r, 0.0)
    jtj = jnp.einsum("knp,knq->pq", jac, jac)
    jtr = jnp.einsum("knp,kn->p", jac, rf)
    dep = jnp.sum(jnp.abs(jac), axis=1) > 0
    return _losses(r), jtj, jtr, dep


def _pad_vec(x: Array, size: int) -> Array:
    return jnp.pad(x, [(0, 0)] * (x.ndim - 1) + [(0, size - x.shape[-1])])


def _pad_mat(x: Array, size: int) -> Array:
    extra = size - x.shape[-1]
    return jnp.pad(x, [(0, 0)] * (x.ndim - 2) + [(0, extra), (0, extra)])


def _closure(dep: Array) -> Array:
    """Boolean ``[C, K, K]``: outputs k, l are coupled through (chains of) shared parameters."""
    depf = dep.astype(jnp.float64)
    a = jnp.einsum("ckp,clp->ckl", depf, depf) > 0
    a = a | jnp.eye(a.shape[-1], dtype=bool)
    for _ in range(max(1, int(np.ceil(np.log2(max(a.shape[-1], 2)))))):
        af = a.astype(jnp.float64)
        a = jnp.einsum("ckl,clm->ckm", af, af) > 0
    return a


def _group_sum(coupled: Array, loss: Array) -> Array:
    """Per-output sum of the losses of its group: ``[C, R, K]`` (inf-safe)."""
    return jnp.sum(jnp.where(coupled[:, None, :, :], loss[:, :, None, :], 0.0), axis=-1)


# ---------------------------------------------------------------------------------------------
# The fused fit


def _initial_params(model: _Model, key_data: np.ndarray, config: FitConfig) -> np.ndarray:
    """``[restarts, n_params]`` starting points (see the module docstring), drawn on the host."""
    rng = np.random.default_rng([*(int(x) for x in key_data.ravel()), model.seed])
    shape = (config.restarts, model.n_params)
    r = config.init_log10_range
    p0 = np.where(rng.random(shape) < 0.5, -1.0, 1.0) * 10.0 ** rng.uniform(-r, r, shape)
    if config.first_restart_ones:
        p0[0] = 1.0
    return p0


def _build(models: tuple[_Model, ...], n_outputs: int, config: FitConfig) -> Callable:
    """The jitted fit of a batch: ``(data, targets, scale, key) -> arrays``."""
    n_out = n_outputs
    pmax = max(m.n_params for m in models)

    def evaluate_all(data, targets, scale, p):  # p [C, R, Pmax]
        outs = [
            jax.vmap(lambda q, m=m: _linearise(m, data, targets, scale, q))(p[c, :, : m.n_params])
            for c, m in enumerate(models)
        ]
        loss = jnp.stack([o[0] for o in outs])
        jtj = jnp.stack([_pad_mat(o[1], pmax) for o in outs])
        jtr = jnp.stack([_pad_vec(o[2], pmax) for o in outs])
        dep = jnp.stack([jnp.any(_pad_vec(o[3], pmax), axis=0) for o in outs])  # [C, K, P]
        return loss, jtj, jtr, dep

    def adam(data, targets, scale, p):
        schedule = optax.cosine_decay_schedule(config.learning_rate, config.adam_steps)
        opt = optax.adam(schedule)

        def total(m, q):
            t = jnp.sum(_losses(_residual(m, data, targets, scale, q)))
            return jnp.where(jnp.isfinite(t), t, 1e300)

        ps = [p[c, :, : m.n_params] for c, m in enumerate(models)]
        states = [jax.vmap(opt.init)(q) for q in ps]

        def step(carry, _):
            ps, states = carry
            new_ps, new_states = [], []
            for m, q, s in zip(models, ps, states, strict=True):
                g = jax.vmap(jax.grad(functools.partial(total, m)))(q)
                g = jnp.where(jnp.isfinite(g), g, 0.0)
                upd, s = jax.vmap(opt.update)(g, s, q)
                q_new = q + upd
                new_ps.append(jnp.where(jnp.isfinite(q_new), q_new, q))
                new_states.append(s)
            return (new_ps, new_states), None

        (ps, _), _ = lax.scan(step, (ps, states), None, length=config.adam_steps)
        return jnp.stack([_pad_vec(q, pmax) for q in ps])

    def fit(data, targets, scale, p):
        if config.adam_steps > 0:
            p = adam(data, targets, scale, p)
        return _levenberg_marquardt(
            lambda q, need, prev: evaluate_all(data, targets, scale, q), p, n_out, config
        )

    return _compiled_caller(jax.jit(fit), config)


def _levenberg_marquardt(evaluate_all: Callable, p: Array, n_out: int, config: FitConfig):
    """The batched LM loop (module docstring, step 3) from ``p [C, R, Pmax]``.

    ``evaluate_all(p, need, previous)`` returns losses ``[C, R, K]``, ``J^T J`` ``[C, R, P, P]``,
    ``J^T r`` ``[C, R, P]`` and the dependence of outputs on parameters ``[C, K, P]``. It may skip
    the outputs whose ``need [C, K]`` is False (their whole group has converged at every restart,
    so none of their parameters moves) and return their ``previous [C, R, K]`` losses.
    """
    n_models, n_restarts, pmax = p.shape
    shape = (n_models, n_restarts, n_out)
    eye = jnp.eye(pmax)

    def cond(s):
        return (s["it"] < config.polish_steps + 1) & ~jnp.all(s["done"])

    def body(s):
        dep = s["dep"]
        active = ~s["done"]  # [C, R, K]
        # parameter j of restart r moves if any active output depends on it
        dep_r = dep[:, None, :, :]  # [C, 1, K, P]
        move = jnp.any(dep_r & active[..., None], axis=2)  # [C, R, P]
        lam_p = jnp.max(jnp.where(dep_r, s["lam"][..., None], 0.0), axis=2)  # [C, R, P]
        d = jnp.diagonal(s["jtj"], axis1=-2, axis2=-1)
        d = jnp.maximum(d, 1e-12 * jnp.max(d, axis=-1, keepdims=True) + 1e-300)
        mm = move[..., :, None] & move[..., None, :]
        a = jnp.where(mm, s["jtj"] + (lam_p * d)[..., None] * eye, eye)
        g = jnp.where(move, s["jtr"], 0.0)
        dp = jax.scipy.linalg.cho_solve(jax.scipy.linalg.cho_factor(a), -g[..., None])
        # the first pass evaluates the starting points themselves
        p_try = jnp.where(move & (s["it"] > 0), s["p"] + dp[..., 0], s["p"])
        first = s["it"] == 0
        group = _closure(dep)
        need = jnp.any(group & jnp.any(active, axis=1)[:, None, :], axis=-1) | first
        loss_t, jtj_t, jtr_t, dep_t = evaluate_all(p_try, need, s["loss"])
        dep_new = dep | dep_t
        coupled = _closure(dep_new)
        lg = _group_sum(coupled, s["loss"])
        lg_t = _group_sum(coupled, loss_t)
        ok = (jnp.isfinite(lg_t) & (lg_t < lg) & active) | first  # [C, R, K]
        acc_p = jnp.any(dep_new[:, None] & ok[..., None], axis=2) | first  # [C, R, P]
        acc_pp = acc_p[..., :, None] & acc_p[..., None, :]
        gain = (lg - lg_t) / jnp.where(lg > 0, lg, 1.0)
        lam_new = jnp.where(ok, s["lam"] * config.damping_down, s["lam"] * config.damping_up)
        lam_new = jnp.where(first, config.damping, jnp.clip(lam_new, 1e-15, 1e300))
        # a group is done when all of its outputs agree it is (damping is shared)
        conv = (ok & (gain < config.ftol)) | (lam_new > config.max_damping) | (lg_t == 0)
        # the step just tried was negligible for every parameter of the output: stationary
        rel = jnp.abs(p_try - s["p"]) / (jnp.abs(s["p"]) + 1e-300)  # [C, R, P]
        big = jnp.any(dep_new[:, None] & (rel > config.xtol)[:, :, None, :], axis=-1)
        conv = conv | (~big & ~first) | ~jnp.any(dep_new, axis=-1)[:, None, :]
        conv = jnp.all(jnp.where(coupled[:, None], conv[:, :, None, :], True), axis=-1)
        return {
            "p": jnp.where(acc_p, p_try, s["p"]),
            "loss": jnp.where(ok, loss_t, s["loss"]),
            "jtj": jnp.where(acc_pp, jtj_t, s["jtj"]),
            "jtr": jnp.where(acc_p, jtr_t, s["jtr"]),
            "dep": dep_new,
            "lam": lam_new,
            "done": (s["done"] | conv) & ~first,
            "it": s["it"] + 1,
        }

    init = {
        "p": p,
        "loss": jnp.full(shape, jnp.inf),
        "jtj": jnp.broadcast_to(eye, (*shape[:2], pmax, pmax)),
        "jtr": jnp.zeros((*shape[:2], pmax)),
        "dep": jnp.zeros((n_models, n_out, pmax), dtype=bool),
        "lam": jnp.full(shape, config.damping),
        "done": jnp.zeros(shape, dtype=bool),
        "it": jnp.zeros((), dtype=jnp.int32),
    }
    s = lax.while_loop(cond, body, init)
    return s["p"], s["loss"], s["dep"], s["it"]


def _compiled_caller(jitted: Any, config: FitConfig, export_key: str | None = None) -> Callable:
    """Call ``jitted``, compiling once per argument signature with ``config.compiler_options``.

    With ``export_key`` and JAX's persistent compilation cache configured
    (``jax_compilation_cache_dir``), the traced and lowered function is also stored there with
    ``jax.export`` so that a later process skips tracing and lowering as well as compiling.
    """
    compiled: dict[Any, Callable] = {}

    def call(*args: Any) -> Any:
        sig = jax.tree.map(lambda x: (x.shape, x.dtype), args)
        sig = (jax.tree.structure(args), tuple(jax.tree.leaves(sig)))
        if sig not in compiled:
            lowered = _exported(jitted, args, export_key, sig) if export_key else None
            lowered = lowered or jitted.lower(*args)
            options = dict(config.compiler_options)
            try:
                compiled[sig] = lowered.compile(options or None)
            except Exception:
                if not options:
                    raise
                compiled[sig] = lowered.compile()  # an option this XLA does not know
        return compiled[sig](*args)

    return call


def _exported(jitted: Any, args: tuple, key: str, sig: Any) -> Any:
    """``jitted`` lowered through a ``jax.export`` kept in the persistent cache directory."""
    cache_dir = jax.config.jax_compilation_cache_dir
    if not cache_dir:
        return None
    import hashlib
    import pathlib

    modules = (interp, interp.sk, _this_module())  # the interpreter, its functions, the LM
    sources = b"".join(pathlib.Path(m.__file__).read_bytes() for m in modules)
    digest = hashlib.sha256(repr((key, str(sig), jax.__version__)).encode() + sources).hexdigest()[
        :32
    ]
    path = pathlib.Path(cache_dir) / f"jaxdmd-fit-{digest}.jaxexport"
    try:
        if path.exists():
            exported = jax.export.deserialize(bytearray(path.read_bytes()))
        else:
            blob = jax.export.export(jitted)(*args).serialize()
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_suffix(f".tmp{np.random.randint(1 << 30)}")
            tmp.write_bytes(blob)
            tmp.replace(path)
            exported = jax.export.deserialize(blob)
        return jax.jit(exported.call).lower(*args)
    except Exception:  # no flatbuffers, an unreadable or incompatible file: trace as usual
        return None


def _this_module() -> Any:
    import sys

    return sys.modules[__name__]


@functools.lru_cache(maxsize=16)
def _cached_build(models: tuple[_Model, ...], n_outputs: int, config: FitConfig) -> Callable:
    return _build(models, n_outputs, config)


@functools.lru_cache(maxsize=32)
def _interpreter_build(
    n_regs: int, n_outputs: int, config: FitConfig, has_operator: bool
) -> Callable:
    """The ONE jitted fit of any batch of programs (see :mod:`jaxdmd.interp`).

    Called as ``fn(code, X, targets, scale, op_index, op_weight, p)`` with ``code`` the packed
    programs ``[C, L]``, ``X`` the variables ``[V, N]`` and ``p`` ``[C, R, P]``. Every shape is a
    bucket (see :func:`_run_interpreter`), so the executable is reused from round to round; the
    candidates are run one after the other (``lax.map``) so that the opcode of the interpreter's
    ``lax.switch`` is never batched, restarts and Jacobian columns are vmapped.
    """

    def evaluate_all(code, pidx, X, targets, scale, op_index, op_weight, p, need, previous):
        n_c, n_r, n_p = p.shape
        n_l = pidx.shape[-1]
        pmask = (pidx >= 0).astype(p.dtype)  # [C*K, Pl]
        slot_k = jnp.tile(jnp.arange(n_outputs), n_c)
        slot_c = jnp.repeat(jnp.arange(n_c), n_outputs)

        def slot(args):
            code_s, pidx_s, pmask_s, k, c, need_s, prev_s = args

            def compute(_):
                q = p[c][:, jnp.maximum(pidx_s, 0)] * pmask_s  # [R, Pl]
                val, jac = interp.run(code_s, X, q, n_regs)
                val, jac = val[:, 0], jac[:, 0]  # [R, N], [R, Pl, N]
                if has_operator:
                    val = jnp.sum(val[..., op_index] * op_weight, axis=-1)
                    jac = jnp.sum(jac[..., op_index] * op_weight, axis=-1)
                r = (val - targets[k]) * scale[k]
                jac = jac * (scale[k] * pmask_s[:, None])
                jac = jnp.where(jnp.isfinite(jac), jac, 0.0)
                rf = jnp.where(jnp.isfinite(r), r, 0.0)
                jtj = jnp.einsum("rpn,rqn->rpq", jac, jac)
                jtr = jnp.einsum("rpn,rn->rp", jac, rf)
                dep = jnp.any(jnp.sum(jnp.abs(jac), axis=-1) > 0, axis=0)
                return _losses(r), jtj, jtr, dep

            def skip(_):
                z = jnp.zeros((n_r, n_l), p.dtype)
                return prev_s, z[:, :, None] * z[:, None, :], z, jnp.zeros((n_l,), bool)

            return lax.cond(need_s, compute, skip, None)

        prev = jnp.swapaxes(previous, 1, 2).reshape(n_c * n_outputs, n_r)
        args = (code, pidx, pmask, slot_k, slot_c, need.reshape(-1), prev)
        loss, jtj, jtr, dep = lax.map(slot, args)
        # back to global parameter indices: one-hot [C, K, Pl, P]
        onehot = (pidx[..., None] == jnp.arange(n_p)).astype(p.dtype)
        onehot = onehot.reshape(n_c, n_outputs, n_l, n_p)
        jtj = jtj.reshape(n_c, n_outputs, n_r, n_l, n_l)
        jtr = jtr.reshape(n_c, n_outputs, n_r, n_l)
        jtj = jnp.einsum("ckap,ckrab,ckbq->crpq", onehot, jtj, onehot)
        jtr = jnp.einsum("ckap,ckra->crp", onehot, jtr)
        dep = jnp.einsum("ckap,cka->ckp", onehot, dep.reshape(n_c, n_outputs, n_l)) > 0
        loss = jnp.swapaxes(loss.reshape(n_c, n_outputs, n_r), 1, 2)
        return loss, jtj, jtr, dep

    def adam(evaluate, p):
        schedule = optax.cosine_decay_schedule(config.learning_rate, config.adam_steps)
        opt = optax.adam(schedule)

        def step(carry, _):
            q, state = carry
            need = jnp.ones((q.shape[0], n_outputs), bool)
            prev = jnp.zeros((*q.shape[:2], n_outputs), q.dtype)
            g = 2.0 * evaluate(q, need, prev)[2]  # d(sum NMSE)/dp = 2 J^T r (non-finite: 0)
            upd, state = opt.update(g, state, q)
            q_new = q + upd
            return (jnp.where(jnp.isfinite(q_new), q_new, q), state), None

        (p, _), _ = lax.scan(step, (p, opt.init(p)), None, length=config.adam_steps)
        return p

    def fit(code, pidx, X, targets, scale, op_index, op_weight, p):
        evaluate = functools.partial(
            evaluate_all, code, pidx, X, targets, scale, op_index, op_weight
        )
        if config.adam_steps > 0:
            p = adam(evaluate, p)
        return _levenberg_marquardt(evaluate, p, n_outputs, config)

    key = repr(("interpreter", n_regs, n_outputs, config, has_operator))
    return _compiled_caller(jax.jit(fit), config, export_key=key)


# ---------------------------------------------------------------------------------------------
# Checking candidates and the public entry point


def _mismatch(skeleton: SkeletonLike, data: Mapping[str, Any], n_outputs: int) -> str | None:
    """Why a candidate cannot be fitted to these data at all (unknown names, output count)."""
    missing = [a for a in skeleton.arguments if a not in data]
    if missing:
        return f"unknown variable(s): {', '.join(missing)}"
    if int(skeleton.n_outputs) != n_outputs:
        return f"has {skeleton.n_outputs} outputs, the targets have {n_outputs}"
    return None


def _check(
    skeleton: SkeletonLike,
    data: Mapping[str, Array],
    targets: Array,
    scale: Array,
    operator: Operator | None = None,
) -> tuple[_Model | None, str | None]:
    """Trace a candidate alone (no XLA compile); return the model or the reason to drop it."""
    n_outputs = targets.shape[0]
    try:
        arguments = tuple(skeleton.arguments)
        mismatch = _mismatch(skeleton, data, n_outputs)
        if mismatch is not None:
            return None, mismatch
        n_params = max(1, int(skeleton.n_params))
        seed = zlib.crc32(str(skeleton.source).encode()) & 0x7FFFFFFF
        model = _Model(skeleton.fn, arguments, n_params, seed, operator)
        p = jax.ShapeDtypeStruct((n_params,), jnp.float64)
        jax.eval_shape(lambda q: _linearise(model, data, targets, scale, q), p)
    except Exception as exc:
        return None, f"failed to trace: {type(exc).__name__}: {exc}"
    return model, None


def _probes(n_params: int, seed: int) -> np.ndarray:
    """``p = 0``, the unit vectors and two random points: ``[n_params + 3, n_params]``."""
    rng = np.random.default_rng(seed)
    return np.concatenate(
        [np.zeros((1, n_params)), np.eye(n_params), rng.normal(0, 3, (2, n_params))]
    )


_EMPTY = interp.Program(
    arguments=(), n_params=0, ops=np.zeros(0, np.int32), a=np.zeros(0, np.int32),
    b=np.zeros(0, np.int32), c=np.zeros(0, np.int32), dst=np.zeros(0, np.int32),
    imm=np.zeros(0), outputs=np.zeros(1, np.int32), n_regs=1, params=np.zeros(0, np.int32),
    kinds=np.zeros((0, 3), np.int32), consts=np.zeros((0, 3)),
)  # fmt: skip


# elements of the predictions ``[probes, K, N]`` that :func:`_by_probes` evaluates at a time
PROBE_CHUNK = 1 << 22


def _by_probes(
    predict: Callable[[np.ndarray], np.ndarray], n_outputs: int, n: int
) -> Callable[[np.ndarray], np.ndarray]:
    """``values_at(probes [B, P]) -> [B, K, N]`` for :func:`_linear_fit` from ``predict(probes)``,
    the predictions at a few probes: the probes go a few at a time (about :data:`PROBE_CHUNK`
    elements), so that the evaluation's temporaries (registers, the operator's product) stay
    that small. Every probe's predictions are computed element-wise, by the same operations as
    with all probes at once (same to the last bit)."""

    def values_at(probes: np.ndarray) -> np.ndarray:
        out = np.empty((len(probes), n_outputs, n))
        step = max(1, PROBE_CHUNK // max(1, n_outputs * n))
        for start in range(0, len(probes), step):
            out[start : start + step] = predict(probes[start : start + step])
        return out

    return values_at


def _affine_groups(
    program: interp.Program,
    rows: np.ndarray,
    seed: int,
    targets: np.ndarray,
    scale: np.ndarray,
    band: Any,
    config: FitConfig,
) -> list[tuple[list[int], list[int], np.ndarray, np.ndarray]]:
    """The groups of outputs (linked by shared parameters) that are affine in their parameters,
    each solved exactly by :func:`_linear_fit`: ``(outputs, parameters, values, losses)``. An
    output that reads no parameter is a group of its own, with its loss and no parameters.

    The outputs of a candidate that share no parameter are separate least-squares problems, so
    the linear shortcut applies to each group on its own, and only one group's predictions are
    held at a time (``[P_g + 3, K_g, N]``, not the candidate's ``[P + 3, K, N]``: at long
    recordings the largest array of a fit). Only the other groups are left to the
    Levenberg-Marquardt loop (their slots in the interpreter are empty).
    """
    dep = lm.dependence(program.parts, max(1, program.n_params))
    found = []
    for outs in lm.output_groups(dep):
        group = lm.OutputGroup(program.parts, outs, rows, targets, scale, band)
        n_p = len(group.cols)
        if n_p == 0:
            try:
                residual = scale[outs] * (group.predict(np.zeros((1, 0)))[0] - targets[outs])
            except Exception:  # leave it to the general path, which reports the reason
                continue
            losses = np.sum(residual**2, axis=1)
            if np.all(np.isfinite(losses)):
                found.append((outs, [], np.zeros(0), losses))
            continue

        values_at = _by_probes(group.predict, len(outs), targets.shape[1])
        fitted = _linear_fit(values_at, n_p, seed, targets[outs], scale[outs], config)
        if fitted is not None:
            found.append((outs, group.cols, fitted.params, fitted.losses))
    return found


def _exact_fit(
    groups: list[tuple[list[int], list[int], np.ndarray, np.ndarray]],
    n_params: int,
    n_outputs: int,
    config: FitConfig,
) -> FitResult | None:
    """The fit of a candidate whose every output is in one of :func:`_affine_groups`' solved
    ``groups``; None if some output is not."""
    if sorted(k for outs, *_ in groups for k in outs) != list(range(n_outputs)):
        return None
    params, losses = np.zeros(n_params), np.empty(n_outputs)
    for outs, cols, values, group_losses in groups:
        params[cols] = values
        losses[outs] = group_losses
    return _result(n_params, params, losses, losses[None], config)


def _check_program(
    skeleton: SkeletonLike,
    data: Mapping[str, np.ndarray],
    n_outputs: int,
    operator: Operator | None = None,
) -> tuple[_Model | None, str | None]:
    """:func:`_check` for a lowered skeleton: nothing to trace, only names and counts."""
    arguments = tuple(skeleton.arguments)
    mismatch = _mismatch(skeleton, data, n_outputs)
    if mismatch is not None:
        return None, mismatch
    seed = zlib.crc32(str(skeleton.source).encode()) & 0x7FFFFFFF
    return _Model(skeleton.fn, arguments, max(1, int(skeleton.n_params)), seed, operator), None


def _linear_fit(
    values_at: Callable[[np.ndarray], Any],
    n_params: int,
    seed: int,
    targets: np.ndarray,
    scale: np.ndarray,
    config: FitConfig,
) -> FitResult | None:
    """The exact fit of a candidate that is affine in ``p``; None if it is not affine.

    ``values_at(probes [B, P])`` returns the predictions ``[B, K, N]`` (operator applied). The
    candidate is evaluated at ``p = 0`` and at the unit vectors (on the host in NumPy, a group
    of outputs at a time, for a lowered program: :func:`_affine_groups`; else eagerly op by op:
    nothing is compiled for it), which gives
    ``pred(p) = b + A p`` if it is affine; affinity is then verified at two random points
    (relative tolerance 1e-9). The weighted least-squares problem
    ``min_p sum_k sum_n scale[k, n]**2 (b + A p - target)[k, n]**2`` (the summed NMSE) is solved
    per group of outputs linked by shared parameters, with column equilibration and an SVD
    (minimum-norm where terms are collinear). This is what
    Levenberg-Marquardt converges to in one step, without its compile.
    """
    probes = _probes(n_params, seed)
    try:
        values = np.asarray(values_at(probes), dtype=np.float64)
    except Exception:  # leave it to the general path, which reports the reason
        return None
    if not np.all(np.isfinite(values)):
        return None
    if values.base is not None or not values.flags.writeable:
        values = values.copy()  # the differences are taken in place below
    # a = values[1:P+1] - values[0], in place ([P, K, N]: the largest array of the fit)
    b, a = values[0], np.subtract(values[1 : n_params + 1], values[0], out=values[1 : n_params + 1])
    abs_r_a = _abs_tensordot(a)
    for r, v in zip(probes[n_params + 1 :], values[n_params + 1 :], strict=True):
        affine = b + np.tensordot(r, a, axes=1)
        size = np.abs(b) + abs_r_a(np.abs(r)) + np.abs(v)
        if np.any(np.abs(v - affine) > 1e-9 * (size + 1e-300)):
            return None
    y = scale * (targets - b)  # [K, N]
    # which outputs each parameter moves (scale * a != 0), one parameter at a time
    dep = np.array([np.any(scale * a_j != 0, axis=1) for a_j in a]).reshape(n_params, -1).T
    p = np.zeros(n_params)  # a parameter that changes nothing: 0, the minimum-norm choice
    for outs in lm.output_groups(dep):  # outputs sharing no parameter: separate problems
        cols = np.flatnonzero(dep[outs].any(axis=0))
        if len(cols):
            sa = a[np.ix_(cols, outs)]  # [P_g, K_g, N], a copy
            sa *= scale[outs][None]
            m = sa.reshape(len(cols), -1).T  # [K_g * N, P_g]
            norms = np.linalg.norm(m, axis=0)
            q, *_ = np.linalg.lstsq(np.divide(m, norms, out=m), y[outs].reshape(-1), rcond=None)
            del sa, m
            p[cols] = q / norms
    resid = scale * (b + np.tensordot(p, a, axes=1) - targets)
    losses = np.sum(resid**2, axis=1)
    return _result(n_params, p, losses, losses[None], config)


def _abs_tensordot(a: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
    """``r -> tensordot(r, |a|, axes=1)`` for ``r >= 0`` without the ``|a|`` of all of ``a``
    at once (``[P, K, N]``): over slices of about :data:`PROBE_CHUNK` elements of the last two
    axes. Only the affinity test's tolerance uses it (the sums may differ from one product of
    the whole in the last bits, which moves the 1e-9 tolerance by as little)."""
    flat = a.reshape(a.shape[0], -1)
    step = max(1, PROBE_CHUNK // max(1, a.shape[0]))

    def product(r: np.ndarray) -> np.ndarray:
        out = np.empty(flat.shape[1])
        for start in range(0, flat.shape[1], step):
            out[start : start + step] = r @ np.abs(flat[:, start : start + step])
        return out.reshape(a.shape[1:])

    return product


def _dropped(skeleton: SkeletonLike, n_outputs: int, error: str) -> FitResult:
    return FitResult(
        params=np.full(max(0, int(getattr(skeleton, "n_params", 0))), np.nan),
        losses=np.full(n_outputs, np.inf),
        score=-np.inf,
        error=error,
    )


def _select(
    p: np.ndarray, loss: np.ndarray, dep: np.ndarray, combine: bool
) -> tuple[np.ndarray, np.ndarray]:
    """Best parameters and losses from ``p [R, P]``, ``loss [R, K]``, dependence ``dep [K, P]``.

    With ``combine``, outputs are grouped by shared parameters (connected components of ``dep``)
    and each group takes its best restart; otherwise the best restart overall is taken.
    """
    loss = np.where(np.isnan(loss), np.inf, loss)
    best = int(np.argmin(np.sum(loss, axis=1)))
    if not combine:
        return p[best].copy(), loss[best].copy()
    params, losses = p[best].copy(), loss[best].copy()
    for outs in lm.output_groups(dep):
        r = int(np.argmin(np.sum(loss[:, outs], axis=1)))
        losses[outs] = loss[r, outs]
        cols = np.any(dep[outs], axis=0)
        params[cols] = p[r, cols]
    return params, losses


def _result(
    n_params: int, params: np.ndarray, losses: np.ndarray, restarts: np.ndarray, config: FitConfig
) -> FitResult:
    params = params[:n_params]
    error = None
    if not np.all(np.isfinite(losses)):
        bad = [int(k) for k in np.flatnonzero(~np.isfinite(losses))]
        error = f"non-finite loss at every restart (outputs {bad})"
    elif not np.all(np.isfinite(params)):
        error = "non-finite parameters"
    elif float(np.mean(losses)) > config.max_nmse:
        error = f"diverged: mean NMSE {float(np.mean(losses)):.3g} > max_nmse {config.max_nmse:g}"
    score = -np.inf if error else -float(np.mean(losses))
    return FitResult(
        params=params, losses=losses, score=score, error=error, restart_losses=restarts
    )


def fit_batch(
    skeletons: Sequence[SkeletonLike],
    variables: Mapping[str, Any],
    targets: Any,
    *,
    key: Array,
    config: FitConfig = FitConfig(),
    weights: Any | None = None,
    operator: Operator | None = None,
) -> list[FitResult]:
    """Fit every candidate (with ``config.restarts`` restarts each) in one compiled call.

    Args:
        skeletons: the candidates; all must have ``n_outputs == targets.shape[0]``.
        variables: variable name -> samples ``[N]`` (several recordings may be concatenated).
        targets: ``[n_outputs, N]`` (DE loop: state-derivative estimates; AE loop: measured
            algebraic variables). A ``[N]`` array is taken as one output.
        key: a JAX PRNG key; the result is deterministic given the key.
        config: see :class:`FitConfig`.
        weights: optional non-negative sample weights, broadcastable to ``[n_outputs, N]``.
        operator: optional :class:`Operator` applied to every output's predictions before the
            comparison (e.g. the smoothing matched to the derivative estimates of the targets).

    Returns:
        One :class:`FitResult` per candidate, in order. Dropped candidates have
        ``score == -inf`` and the reason in ``error``.

    Raises:
        ValueError: if the data themselves are unusable (shapes, non-finite targets, negative
            weights). A bad *candidate* never raises.
    """
    targets_np = np.asarray(targets, dtype=np.float64)
    if targets_np.ndim == 1:
        targets_np = targets_np[None, :]
    if targets_np.ndim != 2:
        raise ValueError(f"targets must be [n_outputs, N], got shape {targets_np.shape}")
    n_outputs, n = targets_np.shape
    if not np.all(np.isfinite(targets_np)):
        raise ValueError("targets contain non-finite values")
    data_np = {str(k): np.asarray(v, dtype=np.float64) for k, v in variables.items()}
    for name, v in data_np.items():
        if v.shape != (n,):
            raise ValueError(f"variable {name!r} has shape {v.shape}, expected ({n},)")
    w = np.ones_like(targets_np) if weights is None else np.asarray(weights, dtype=np.float64)
    w = np.broadcast_to(w, targets_np.shape)
    if np.any(~np.isfinite(w)) or np.any(w < 0):
        raise ValueError("weights must be finite and non-negative")
    if config.restarts < 1:
        raise ValueError("config.restarts must be >= 1")
    if config.backend not in ("host", "xla"):
        raise ValueError(f"config.backend must be 'host' or 'xla', got {config.backend!r}")
    if operator is not None and (
        operator.index.shape[0] != n or int(operator.index.max(initial=0)) >= n
    ):
        raise ValueError(f"the operator does not fit {n} samples")

    scale_np = np.sqrt(w / (n * _variance(targets_np)[:, None]))
    data = {k: _on_device(v) for k, v in data_np.items()}
    tgt, scale = _on_device(targets_np), _on_device(scale_np)

    results: list[FitResult | None] = [None] * len(skeletons)
    models: dict[int, _Model] = {}
    programs: dict[int, interp.Program] = {}
    for i, sk in enumerate(skeletons):
        program = interp.program_of(sk) if config.interpreter else None
        if program is not None:
            model, error = _check_program(sk, data_np, n_outputs, operator)
            if model is not None:
                programs[i] = program
        else:
            model, error = _check(sk, data, tgt, scale, operator)
        if model is None:
            results[i] = _dropped(sk, n_outputs, error or "unknown error")
        else:
            models[i] = model

    # groups of outputs of a lowered candidate that are affine in their own parameters:
    # candidate -> [(outputs, parameters, exact parameters, exact losses)]
    exact: dict[int, list[tuple[list[int], list[int], np.ndarray, np.ndarray]]] = {}

    def finish(indices: list[int], out: Any) -> None:
        p, loss, dep, _ = (np.asarray(x) for x in jax.device_get(out))
        for j, i in enumerate(indices):
            params, losses = _select(p[j], loss[j], dep[j], config.combine_restarts)
            restarts = loss[j].copy()
            for outs, cols, exact_params, exact_losses in exact.get(i, []):
                params[cols] = exact_params
                losses[outs] = exact_losses
                restarts[:, outs] = exact_losses
            results[i] = _result(int(skeletons[i].n_params), params, losses, restarts, config)

    def run(indices: list[int]) -> None:
        batch = tuple(models[i] for i in indices)
        used = sorted({a for m in batch for a in m.arguments})
        fn = _cached_build(batch, n_outputs, config)
        pmax = max(m.n_params for m in batch)
        p0 = np.zeros((len(batch), config.restarts, pmax))
        for j, m in enumerate(batch):
            p0[j, :, : m.n_params] = _initial_params(m, key_data, config)
        finish(indices, fn({a: data[a] for a in used}, tgt, scale, _on_device(p0)))

    # each lowered candidate's feature rows [F, N], kept while the candidate is being fitted
    # (the linear shortcut, its affine groups and Levenberg-Marquardt read them) and dropped when
    # it is done: at long recordings the rows of a whole batch would not fit in memory
    features: dict[int, np.ndarray] = {}

    def feature_values(i: int) -> np.ndarray:
        if i not in features:
            args = [data_np[a] for a in programs[i].arguments]
            features[i] = programs[i].feature_values(args)
        return features[i]

    def run_programs(indices: list[int]) -> None:
        chunk = max(1, config.interpreter_chunk)
        pmax = interp.bucket(max(models[i].n_params for i in indices), 4)
        parts_of = {i: programs[i].parts for i in indices}
        n_local = interp.bucket(max(q.n_params for i in indices for q in parts_of[i]), 2)
        n_regs = interp.bucket(max(q.n_regs for i in indices for q in parts_of[i]), 8)
        fn = _interpreter_build(n_regs, n_outputs, config, operator is not None)
        if operator is None:
            op_index = _on_device(np.zeros((1, 1), np.int64))
            op_weight = _on_device(np.zeros((1, 1)))
        else:
            op_index, op_weight = operator.index, operator.weight
        chunks = [indices[s : s + chunk] for s in range(0, len(indices), chunk)]
        n_rows = interp.bucket(max(sum(len(feature_values(i)) for i in c) for c in chunks), 16)
        for part in chunks:
            rows = [feature_values(i) for i in part]
            offsets = np.cumsum([0] + [len(r) for r in rows])[:-1]
            x = np.zeros((n_rows, n))
            x[: sum(len(r) for r in rows)] = np.concatenate(rows)
            solved = {i: {k for outs, *_ in exact.get(i, []) for k in outs} for i in part}
            slots = [
                _EMPTY if k in solved[i] else q for i in part for k, q in enumerate(parts_of[i])
            ]
            slot_offsets = [o for o, i in zip(offsets, part, strict=True) for _ in parts_of[i]]
            code = interp.pack(slots, slot_offsets, interp.MAX_INSTRUCTIONS, chunk * n_outputs)
            pidx = np.full((chunk * n_outputs, n_local), -1, np.int32)
            for j, q in enumerate(slots):
                pidx[j, : q.n_params] = q.params
            p0 = np.zeros((chunk, config.restarts, pmax))
            for j, i in enumerate(part):
                p0[j, :, : models[i].n_params] = _initial_params(models[i], key_data, config)
            code_j = {k: _on_device(v) for k, v in code.items()}
            args = (_on_device(x), tgt, scale, op_index, op_weight, _on_device(p0))
            finish(part, fn(code_j, _on_device(pidx), *args))

    def run_host(indices: list[int]) -> None:
        for i in indices:
            solved = {k for outs, *_ in exact.get(i, []) for k in outs}
            p0 = _initial_params(models[i], key_data, config)
            p, loss, dep, steps = lm.fit_programs(
                programs[i].parts, feature_values(i), targets_np, scale_np, p0, config, band,
                solved,
            )  # fmt: skip
            finish([i], (p[None], loss[None], dep[None], steps))
            features.pop(i, None)

    def values_at(i: int) -> Callable[[np.ndarray], Any]:
        model = models[i]
        return lambda probes: jax.vmap(lambda q: _predict(model, data, q, n_outputs))(
            jnp.asarray(probes)
        )

    key_data = np.asarray(jax.random.key_data(key))
    band = None if operator is None else operator.band
    if config.linear_shortcut:
        for i in list(models):
            m = models[i]
            if i in programs:  # a group of outputs at a time; the rest is left to LM below
                exact[i] = _affine_groups(
                    programs[i], feature_values(i), m.seed, targets_np, scale_np, band, config
                )
                fitted = _exact_fit(exact[i], m.n_params, n_outputs, config)
            else:
                fitted = _linear_fit(values_at(i), m.n_params, m.seed, targets_np, scale_np, config)
            if fitted is not None:
                n_real = int(skeletons[i].n_params)
                results[i] = dataclasses.replace(fitted, params=fitted.params[:n_real])
                del models[i]
                features.pop(i, None)
                exact.pop(i, None)
    lowered = [i for i in models if i in programs]
    if lowered:
        try:
            if config.backend == "host" and config.adam_steps == 0:
                run_host(lowered)
            else:
                run_programs(lowered)
        except Exception:  # the interpreter failed (a bug): fit these through their functions
            for i in lowered:
                del programs[i]
                model, error = _check(skeletons[i], data, tgt, scale, operator)
                if model is None:
                    results[i] = _dropped(skeletons[i], n_outputs, error or "unknown error")
                    del models[i]
    rest = [i for i in models if i not in programs]
    if rest:
        try:
            run(rest)
        except Exception:
            # a candidate broke the fused compile or run: fit one by one to isolate it
            for i in rest:
                try:
                    run([i])
                except Exception as exc:
                    results[i] = _dropped(
                        skeletons[i], n_outputs, f"fit failed: {type(exc).__name__}: {exc}"
                    )
    return [r for r in results if r is not None]
