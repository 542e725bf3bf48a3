"""Levenberg-Marquardt on the host: the interpreter fit of :mod:`jaxdmd.fit` without a compile.

A round's nonlinear least-squares problems are small (one output's program, 1 to 4 of its own
parameters, a few thousand samples, 8 restarts), so the time of a fit is dominated by the XLA
compile of the jitted interpreter fit (about 1.5 s of CPU per process, before the first round
can run) rather than by its arithmetic. Here the same algorithm runs in NumPy on the lowered
programs (:func:`jaxdmd.interp.run_numpy`): nothing is traced or compiled, so the first round of
a process costs what every later round costs.

Algorithm (the same as ``fit._levenberg_marquardt``, per group of outputs linked by shared
parameters): Marquardt-scaled normal equations ``(J^T J + lambda diag J^T J) dp = -J^T r`` for
all active restarts of the group at once; a trial point is accepted when the group's summed
NMSE falls (a non-finite trial is rejected like an uphill one); ``lambda`` is multiplied by
``damping_down`` after an accepted step and by ``damping_up`` after a rejected one; a restart
stops when an accepted step gains less than ``ftol`` (relative), when the step just tried moves
every parameter by less than ``xtol`` (relative), when ``lambda`` exceeds ``max_damping``, when
its loss is exactly 0, or after ``polish_steps`` steps. What the host does differently, because
it can: a trial point's Jacobian is computed only when the step is accepted (the compiled loop
computes it always), restarts that have stopped are dropped from the arrays instead of being
carried along, and each group runs to its own end instead of waiting for the slowest.
"""

from __future__ import annotations

import contextlib
from collections.abc import Sequence
from typing import Any

import numpy as np

from jaxdmd import interp

__all__ = [
    "OutputGroup", "apply_band", "band_matrix", "dependence", "fit_programs", "output_groups",
]  # fmt: skip


def band_matrix(index: Any, weight: Any) -> Any:
    """The operator ``(S y)_i = sum_k weight[i, k] y[index[i, k]]`` as a SciPy CSR matrix."""
    import scipy.sparse

    index, weight = np.asarray(index), np.asarray(weight, dtype=np.float64)
    n, width = index.shape
    indptr = np.arange(0, n * width + 1, width)
    return scipy.sparse.csr_matrix((weight.ravel(), index.ravel(), indptr), shape=(n, n))


# elements of the rows that :func:`apply_band` sends through the sparse product at a time
BAND_CHUNK = 1 << 22


def apply_band(band: Any, x: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """The sparse matrix ``band`` (:func:`band_matrix`) along the last axis of ``x``.

    The rows of ``x`` (all axes but the last) go through the product a few at a time (about
    :data:`BAND_CHUNK` elements), so the temporaries (SciPy's C-ordered copy of the operand, the
    product, its transpose) stay that small whatever the size of ``x``; each row's result is the
    same to the last bit as in one product of all rows (SciPy's CSR product runs every column
    of its operand through the same sum, in the same order). ``out`` (``x`` itself allowed)
    receives the result; by default a new array.
    """
    flat = x.reshape(-1, x.shape[-1])
    if out is None:
        out = np.empty(x.shape, dtype=np.result_type(x.dtype, band.dtype))
    result = out.reshape(flat.shape)
    rows = max(1, BAND_CHUNK // max(1, flat.shape[1]))
    for start in range(0, flat.shape[0], rows):
        result[start : start + rows] = (band @ flat[start : start + rows].T).T
    return out


def output_groups(dep: np.ndarray) -> list[list[int]]:
    """The outputs linked by shared parameters (connected components of ``dep [K, P]``: output
    ``k`` depends on parameter ``j``), in order of their first output; an output with no
    parameter is a group of its own."""
    n_out = dep.shape[0]
    root = list(range(n_out))

    def find(k: int) -> int:
        while root[k] != k:
            k = root[k]
        return k

    for j in range(dep.shape[1]):
        users = np.flatnonzero(dep[:, j])
        for k in users[1:]:
            root[find(int(k))] = find(int(users[0]))
    groups: dict[int, list[int]] = {}
    for k in range(n_out):
        groups.setdefault(find(k), []).append(k)
    return list(groups.values())


def dependence(parts: Sequence[interp.Program], n_params: int) -> np.ndarray:
    """``[K, P]``: which parameters each output program reads."""
    dep = np.zeros((len(parts), n_params), dtype=bool)
    for k, part in enumerate(parts):
        dep[k, part.params] = True
    return dep


class OutputGroup:
    """The least-squares problem of one group of outputs over its own parameters ``cols`` (the
    candidate's parameters the group's programs read, in order)."""

    def __init__(
        self,
        parts: Sequence[interp.Program],
        outputs: Sequence[int],
        rows: np.ndarray,
        targets: np.ndarray,
        scale: np.ndarray,
        band: Any,
    ) -> None:
        self.cols = sorted({g for k in outputs for g in parts[k].params.tolist()})
        position = {g: j for j, g in enumerate(self.cols)}
        self.terms = [
            (parts[k], np.array([position[g] for g in parts[k].params.tolist()], np.intp), k)
            for k in outputs
        ]
        self.rows, self.targets, self.scale, self.band = rows, targets, scale, band

    def evaluate(self, q: np.ndarray, jacobian: bool) -> tuple[np.ndarray, Any, Any]:
        """Per-output NMSE ``[B, K_g]`` at ``q [B, P_g]``, and ``J^T J``, ``J^T r`` if asked.

        Non-finite residuals give an infinite loss; non-finite Jacobian entries count as 0."""
        n_b, n_p = q.shape
        n = self.targets.shape[1]
        loss = np.empty((n_b, len(self.terms)))
        jtj = np.zeros((n_b, n_p, n_p)) if jacobian else None
        jtr = np.zeros((n_b, n_p)) if jacobian else None
        for m, (program, local, k) in enumerate(self.terms):
            q_k = q[:, local]
            (value,), (tangent,) = interp.run_numpy(program, self.rows, q_k, jacobian, False)
            r = self._residual(value, k, n_b)
            sq = np.einsum("bn,bn->b", r, r)
            finite = np.isfinite(sq)
            loss[:, m] = np.where(finite, sq, np.inf)
            if not jacobian or tangent is None:
                continue
            if not finite.all():
                r = np.where(np.isfinite(r), r, 0.0)
            a, g = self._products(tangent, r, k, n_b, len(local), n)
            if not (np.isfinite(a).all() and np.isfinite(g).all()):  # rare: the careful way
                (_,), (tangent,) = interp.run_numpy(program, self.rows, q_k, True, True)
                a, g = self._products(tangent, r, k, n_b, len(local), n, mask=True)
            jtj[:, local[:, None], local[None, :]] += a
            jtr[:, local] += g
        return loss, jtj, jtr

    def predict(self, q: np.ndarray) -> np.ndarray:
        """The group's predictions ``[B, K_g, N]`` at ``q [B, P_g]`` (the operator applied)."""
        with np.errstate(all="ignore"):
            values = [
                interp.run_numpy(program, self.rows, q[:, local], False)[0][0]
                for program, local, _ in self.terms
            ]
            return np.stack([self._prediction(v, q.shape[0]) for v in values], axis=1)

    def _prediction(self, value: Any, n_b: int) -> np.ndarray:
        """An output's value from :func:`interp.run_numpy` as ``[B, N]``, the operator applied."""
        value = np.broadcast_to(value, (n_b, self.targets.shape[1]))
        return value if self.band is None else apply_band(self.band, value)

    def _residual(self, value: Any, k: int, n_b: int) -> np.ndarray:
        return (self._prediction(value, n_b) - self.targets[k]) * self.scale[k]

    def _products(
        self, tangent: Any, r: np.ndarray, k: int, n_b: int, n_p: int, n: int, mask: bool = False
    ) -> tuple[np.ndarray, np.ndarray]:
        """``J^T J`` and ``J^T r`` of output ``k`` from its tangent (``mask``: non-finite -> 0)."""
        jac = np.broadcast_to(tangent, (n_b, n_p, n))
        if self.band is not None:
            jac = apply_band(self.band, jac)
        jac = jac * self.scale[k]
        if mask:
            jac = np.where(np.isfinite(jac), jac, 0.0)
        return jac @ np.swapaxes(jac, 1, 2), np.einsum("bpn,bn->bp", jac, r)


def _solve(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Batched ``a^-1 b``; a singular system gives NaN (its trial point is then rejected)."""
    try:
        return np.linalg.solve(a, b[..., None])[..., 0]
    except np.linalg.LinAlgError:
        out = np.full_like(b, np.nan)
        for i in range(len(a)):
            with contextlib.suppress(np.linalg.LinAlgError):
                out[i] = np.linalg.solve(a[i], b[i])
        return out


def _levenberg_marquardt(group: OutputGroup, p0: np.ndarray, config: Any) -> tuple[Any, Any, int]:
    """LM from ``p0 [R, P_g]`` (module docstring): parameters, per-output losses, steps."""
    p = p0.copy()
    loss, jtj, jtr = group.evaluate(p, jacobian=True)
    total = loss.sum(axis=1)
    lam = np.full(len(p), float(config.damping))
    active = np.arange(len(p))
    eye = np.eye(p.shape[1])
    steps = 0
    while steps < config.polish_steps and len(active):
        steps += 1
        d = np.diagonal(jtj[active], axis1=1, axis2=2)
        d = np.maximum(d, 1e-12 * d.max(axis=1, keepdims=True) + 1e-300)
        a = jtj[active] + (lam[active, None] * d)[:, :, None] * eye
        trial = p[active] + _solve(a, -jtr[active])
        trial_loss, _, _ = group.evaluate(trial, jacobian=False)
        trial_total = trial_loss.sum(axis=1)
        before = total[active]
        ok = np.isfinite(trial_total) & (trial_total < before)
        gain = (before - trial_total) / np.where(before > 0, before, 1.0)
        lam[active] = np.clip(
            lam[active] * np.where(ok, config.damping_down, config.damping_up), 1e-15, 1e300
        )
        moved = np.abs(trial - p[active]) > config.xtol * np.abs(p[active])
        done = (
            (ok & (gain < config.ftol))
            | (lam[active] > config.max_damping)
            | (trial_total == 0)
            | ~np.any(moved, axis=1)
        )
        accepted = active[ok]
        if len(accepted):
            p[accepted] = trial[ok]
            loss[accepted], jtj[accepted], jtr[accepted] = group.evaluate(p[accepted], True)
            total[accepted] = loss[accepted].sum(axis=1)
        active = active[~done]
    return p, loss, steps


def fit_programs(
    parts: Sequence[interp.Program],
    rows: np.ndarray,
    targets: np.ndarray,
    scale: np.ndarray,
    p0: np.ndarray,
    config: Any,
    band: Any = None,
    skip: set[int] = frozenset(),  # type: ignore[assignment]
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Fit one candidate's per-output programs by LM from every restart ``p0 [R, P]``.

    ``parts`` are the candidate's output programs (``Program.parts``: local parameters mapped to
    ``p`` by ``params``), ``rows`` ``[F, N]`` their feature rows, ``targets`` and ``scale``
    ``[K, N]`` (the residual is ``scale * (S pred - target)``, its sum of squares the
    NMSE), ``band`` the sparse operator ``S`` (:func:`band_matrix`) or None, ``config`` a
    :class:`jaxdmd.fit.FitConfig`. Outputs in ``skip`` (solved elsewhere) are not evaluated.

    Returns the parameters ``[R, P]``, per-output losses ``[R, K]`` (0 for skipped outputs), the
    dependence of outputs on parameters ``[K, P]`` and the largest number of LM steps a group took.
    """
    n_r, n_p = p0.shape
    p = np.array(p0, dtype=np.float64)
    loss = np.zeros((n_r, len(parts)))
    dep = np.zeros((len(parts), n_p), dtype=bool)
    steps = 0
    with np.errstate(all="ignore"):
        for k, part in enumerate(parts):
            if k not in skip and not len(part.params):  # nothing to fit: its loss as it is
                fixed = OutputGroup(parts, [k], rows, targets, scale, band)
                loss[:, k] = fixed.evaluate(np.zeros((1, 0)), jacobian=False)[0][0, 0]
        fitted = dependence(parts, n_p)
        fitted[list(skip)] = False
        for outputs in output_groups(fitted):
            if not fitted[outputs].any():
                continue
            group = OutputGroup(parts, outputs, rows, targets, scale, band)
            q, group_loss, n = _levenberg_marquardt(group, p[:, group.cols], config)
            p[:, group.cols] = q
            loss[:, outputs] = group_loss
            dep[outputs] = fitted[outputs]
            steps = max(steps, n)
    return p, loss, dep, steps
