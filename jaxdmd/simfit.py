"""The model's parameters fitted by how it simulates (output error), kept if that generalises.

Every fit before this one is an *equation-error* fit: each equation is fitted to estimated
derivatives, integrals or algebraic values, with the other channels taken from the recording.
Such fits are blind to how errors feed back when the equations run together: an AE equation
whose small bias shifts the closed model's operating point, or a state equation that is
slightly too weakly damped, each fit well alone and simulate badly together. Here the
parameters of the state and algebraic equations are refitted together, by Levenberg-Marquardt,
to the residual of two simulations of every training recording (:func:`refit_simulation`):

- the closed model (the algebraic variables computed by the AE equations: a DAE rollout), and
- the state equations with the measured algebraic variables played in.

The second keeps the state equations honest: fitted to the closed rollout alone, they learn to
compensate the algebraic equations' errors and then simulate badly with the true algebraic
variables (measured on the benchmark: a DE-only test error of 1.4 % rising to 3900 %).

An output-error fit is a better estimator where the model is right and a worse one where it
is not (it fits noise and structure errors into the parameters), so it is only kept if it
generalises: each recording is left out in turn, the parameters are fitted on the others and
the left-out one is simulated; the refit is kept only if the mean left-out error is lower than
the in-sample error of the parameters it starts from by more than the selection's
``tolerance`` (with recordings on different time grids, it is skipped). With one recording its
time blocks are left out instead (:func:`jaxdmd.select.time_blocks`, four of equal duration):
each block's samples are weighted out of the residual in turn, the parameters fitted on the
rest, and the block simulated from the states at its first sample, its error over the block
normalised by the whole recording's range; the given parameters are scored on the same
blocks.

Which structure to refit is itself a choice by simulation (:func:`refit_finalists`): where the
selection (:func:`jaxdmd.select.select_algebraic`) changed the AE loop's lines, both sets are
refitted, and the one whose structure simulates the left-out recordings better once fitted to
simulate is the model; the loop's choice, listed second, must be better by the tolerance.

The simulation is the host simulation's scheme (:func:`jaxdmd.select.simulate_host`: Heun's
method on the sample grid with ``substeps``, inputs linear between samples and held across an
event), written in JAX so that its sensitivities to the parameters are exact; one compiled
program serves every fold. The fit never holds the rollouts' Jacobian: the sensitivities are
carried forward with the states and folded, a chunk of sample intervals at a time, into a QR
factor of the Jacobian beside the residual (:meth:`_Simulator.factor`), on which each
Levenberg-Marquardt step is solved, so its memory does not grow with the recordings' length.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxdmd import lines as ln
from jaxdmd import select, workers
from jaxdmd.data import Dataset
from jaxdmd.search import Equations

__all__ = ["refit_finalists", "refit_simulation"]

_CHUNK = 256  # sample intervals whose sensitivities are held at once (Simulator.factor)


def _played(recordings: Sequence[Dataset], names: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
    """Left and right values ``[B, n - 1, A]`` of the played-in channels on each interval
    (:func:`jaxdmd.select._played`, stacked)."""
    left, right = [], []
    for ds in recordings:
        played, empty = select._played(ds, names), np.zeros((ds.n_samples - 1, 0))
        left.append(np.stack([played.left[a] for a in names], 1) if names else empty)
        right.append(np.stack([played.right[a] for a in names], 1) if names else empty)
    return np.stack(left), np.stack(right)


class _Simulator:
    """The two simulations of every recording as a function of the parameters ``theta``
    (the state equations' parameters, then the algebraic equations')."""

    def __init__(
        self,
        de: Equations,
        ae: Equations,
        measured: Sequence[Dataset],
        played_from: Sequence[Dataset],
        substeps: int,
        blowup: float,
        windows: Sequence[tuple[int, int]] | None = None,
    ) -> None:
        self.de_skeleton, self.ae_skeleton = de.skeleton(), ae.skeleton()
        self.states = tuple(de.contract.targets)
        self.algebraic = tuple(ae.contract.targets)
        self.n_de = len(de.params)
        self.theta0 = np.asarray([*de.params, *ae.params], dtype=float)
        needed = [*self.de_skeleton.arguments, *self.ae_skeleton.arguments]
        # the closed model plays in what is neither a state nor computed; the open one also
        # plays in the measured algebraic variables
        self.closed_names = sorted({a for a in needed if a not in self.states + self.algebraic})
        self.open_names = sorted({a for a in self.de_skeleton.arguments if a not in self.states})
        t = np.asarray(measured[0].t, dtype=float)
        self.h = jnp.asarray(np.diff(t))
        self.closed = tuple(jnp.asarray(x) for x in _played(played_from, self.closed_names))
        self.open = tuple(jnp.asarray(x) for x in _played(played_from, self.open_names))
        self.x0 = jnp.asarray(
            np.stack([[float(np.asarray(ds[s])[0]) for s in self.states] for ds in played_from])
        )
        # held-out time blocks (select.simulate_host's windows): row b holds the played-in
        # states until its block starts, and is scored on its block only
        self.windows = None if windows is None else list(windows)
        self.hold = self.reference = None
        if windows is not None:
            start = np.asarray([a for a, _ in windows])
            self.hold = jnp.asarray(np.arange(1, t.size)[None, :] <= start[:, None])  # [B, n-1]
            states = np.stack(
                [[np.asarray(ds[s], dtype=float) for s in self.states] for ds in played_from]
            )
            self.reference = jnp.asarray(np.swapaxes(states[:, :, 1:], 1, 2))  # [B, n-1, S]
        y = np.stack([[np.asarray(ds[s], dtype=float) for s in self.states] for ds in measured])
        self.y = jnp.asarray(y)  # [B, S, n]
        self.scale = jnp.asarray(select._range(y))
        self.bound = jnp.asarray(blowup * (1.0 + np.max(np.abs(y), axis=2)))  # [B, S]
        self.substeps = substeps
        self._chunked: tuple[jax.Array, ...] | None = None  # factor's inputs, laid out once
        self._folded = jax.jit(self._fold)  # one program for every fit's factor
        # one program for every scoring evaluation (op by op, each cost seconds of compiling)
        self._compiled = jax.jit(self.simulate)

    def _advance(
        self, theta: jax.Array, x: jax.Array, bound: jax.Array, interval: tuple[jax.Array, ...],
        names: Sequence[str], closed: bool,
    ) -> jax.Array:  # fmt: skip
        """One recording's states ``[S]`` one sample interval on: ``interval`` is the step
        ``h``, the played-in channels' left and right values ``[A]`` and, for a held-out
        block, whether the reference ``[S]`` (the next element) replaces the result. A state
        that leaves ``bound`` is held there (finite, so the fit sees a large residual rather
        than a NaN)."""
        de_p, ae_p = theta[: self.n_de], theta[self.n_de :]
        de_p = de_p if self.n_de else jnp.zeros(1)
        ae_p = ae_p if ae_p.size else jnp.zeros(1)
        index = {a: i for i, a in enumerate(names)}

        def field(x: jax.Array, u: jax.Array) -> jax.Array:
            values = {s: x[i] for i, s in enumerate(self.states)}
            values.update({a: u[i] for a, i in index.items()})
            if closed:
                args = [values[a] for a in self.ae_skeleton.arguments]
                out = self.ae_skeleton.fn(*args, ae_p)
                values.update(dict(zip(self.algebraic, out, strict=True)))
            args = [values[a] for a in self.de_skeleton.arguments]
            out = self.de_skeleton.fn(*args, de_p)
            return jnp.stack([jnp.broadcast_to(jnp.asarray(d, dtype=x.dtype), ()) for d in out])

        h, lo, hi = interval[:3]
        dt = h / self.substeps
        for m in range(self.substeps):  # Heun's method, as select.simulate_host
            w0, w1 = m / self.substeps, (m + 1) / self.substeps
            k1 = field(x, (1 - w0) * lo + w0 * hi)
            k2 = field(x + dt * k1, (1 - w1) * lo + w1 * hi)
            x = x + 0.5 * dt * (k1 + k2)
        x = jnp.where(jnp.isfinite(x), jnp.clip(x, -bound, bound), bound)
        if len(interval) > 3:
            x = jnp.where(interval[3], interval[4], x)
        return x

    def _rollout(
        self, theta: jax.Array, names: Sequence[str], left: jax.Array, right: jax.Array,
        x0: jax.Array, bound: jax.Array, closed: bool,
        hold: jax.Array | None = None, reference: jax.Array | None = None,
    ) -> jax.Array:  # fmt: skip
        """One recording's simulated states ``[S, n]`` (:meth:`_advance` from ``x0``).
        ``hold`` and ``reference`` (``[n - 1]``, ``[n - 1, S]``): the states after each step
        are the reference's where ``hold`` is set (before a held-out block starts)."""

        def step(x: jax.Array, interval: tuple[jax.Array, ...]) -> tuple[jax.Array, jax.Array]:
            x = self._advance(theta, x, bound, interval, names, closed)
            return x, x

        inputs = (self.h, left, right) if hold is None else (self.h, left, right, hold, reference)
        _, xs = jax.lax.scan(step, x0, inputs)
        return jnp.concatenate([x0[:, None], xs.T], axis=1)

    def simulate(self, theta: jax.Array) -> tuple[jax.Array, jax.Array]:
        """The closed and the open (algebraic variables played in) rollouts ``[B, S, n]``."""
        runs = ((True, self.closed_names, self.closed), (False, self.open_names, self.open))
        out = []
        for closed, names, (left, right) in runs:
            if self.hold is not None:

                def held(lo: jax.Array, hi: jax.Array, x0: jax.Array, bound: jax.Array,
                         hold: jax.Array, reference: jax.Array, closed: bool = closed,
                         names: Sequence[str] = names) -> jax.Array:  # fmt: skip
                    return self._rollout(theta, names, lo, hi, x0, bound, closed, hold, reference)

                args = (left, right, self.x0, self.bound, self.hold, self.reference)
                out.append(jax.vmap(held)(*args))
                continue

            def one(lo: jax.Array, hi: jax.Array, x0: jax.Array, bound: jax.Array,
                    closed: bool = closed, names: Sequence[str] = names) -> jax.Array:  # fmt: skip
                return self._rollout(theta, names, lo, hi, x0, bound, closed)

            out.append(jax.vmap(one)(left, right, self.x0, self.bound))
        return out[0], out[1]

    def factor(self, weight: np.ndarray) -> Callable[[jax.Array], jax.Array]:
        """The function ``theta -> `` upper-triangular factor ``[P + 1, P + 1]`` of
        ``[J, r]``, without either: the residual ``r`` of both simulations of every recording
        (each sample's error scaled by its state's range and ``sqrt(n)``, times ``weight``
        ``[B, n]`` or ``[B, 1]``: its sum of squares is the weighted sum of the NRMSEs
        squared) beside its Jacobian ``J``.

        The two simulations run with their forward sensitivities (one tangent per parameter,
        carried step by step), ``_CHUNK`` sample intervals at a time; each chunk's rows of
        ``[J, r]`` are folded into the factor by a QR decomposition and dropped, so the
        working memory does not depend on the recordings' length (the chunked inputs are
        laid out here, once per ``weight``). With ``[[R, z], [0, rho]]`` the factor,
        ``|J d + r|^2 = |R d + z|^2 + rho^2`` for every step ``d``."""
        inputs = self._fold_inputs(weight)
        return lambda theta: self._folded(theta, *inputs)

    def _fold_inputs(self, weight: np.ndarray) -> tuple[jax.Array, ...]:
        """:meth:`_fold`'s arguments after ``theta`` for ``weight``: the first sample's
        weights, then the steps, states, weights and played-in channels chunked."""
        b, _, n = self.y.shape
        steps = n - 1
        chunks = -(-steps // _CHUNK)
        pad = chunks * _CHUNK - steps

        def timed(a: np.ndarray) -> jax.Array:  # [B, n - 1, ...] -> [chunks, _CHUNK, B, ...]
            a = np.moveaxis(np.asarray(a, dtype=float), 1, 0)
            a = np.concatenate([a, np.zeros((pad, *a.shape[1:]))])
            return jnp.asarray(a.reshape(chunks, _CHUNK, *a.shape[1:]))

        if self._chunked is None:  # what does not depend on the weight, laid out once
            h = np.concatenate([np.asarray(self.h), np.zeros(pad)]).reshape(chunks, _CHUNK)
            y = timed(np.swapaxes(np.asarray(self.y)[:, :, 1:], 1, 2))
            played = [timed(a) for pair in (self.closed, self.open) for a in pair]
            self._chunked = (jnp.asarray(h), y, *played)
        weight = np.broadcast_to(np.asarray(weight, dtype=float), (b, n))
        norm = 1.0 / np.asarray(self.scale) / np.sqrt(n)  # [B, S]
        w = timed(weight[:, 1:, None] * norm[:, None, :])  # [chunks, _CHUNK, B, S]
        w0 = jnp.asarray(weight[:, 0, None] * norm)
        h, y, *played = self._chunked
        return (w0, h, y, w, *played)

    def _fold(self, theta: jax.Array, w0: jax.Array, *inputs: jax.Array) -> jax.Array:
        """:meth:`factor`'s program: ``w0`` the first sample's weights ``[B, S]``, ``inputs``
        the chunked steps, states, weights and played-in channels (closed, then open):
        :meth:`_fold_inputs`."""
        p = theta.size
        b, s, _ = self.y.shape
        runs = ((self.closed_names, True), (self.open_names, False))

        def advance(names: Sequence[str], closed: bool) -> Callable[..., tuple[jax.Array, ...]]:
            def one(x: jax.Array, dx: jax.Array, bound: jax.Array, h: jax.Array,
                    lo: jax.Array, hi: jax.Array) -> tuple[jax.Array, jax.Array]:  # fmt: skip
                def move(q: jax.Array, z: jax.Array) -> jax.Array:
                    return self._advance(q, z, bound, (h, lo, hi), names, closed)

                x_next, tangent = jax.linearize(move, theta, x)
                return x_next, jax.vmap(tangent)(jnp.eye(p, dtype=theta.dtype), dx)

            return jax.vmap(one, in_axes=(0, 0, 0, None, 0, 0))

        movers = tuple(advance(names, closed) for names, closed in runs)

        def fold(factor: jax.Array, J: jax.Array, r: jax.Array) -> jax.Array:
            rows = jnp.concatenate([J.reshape(-1, p), r.reshape(-1, 1)], axis=1)
            return jnp.linalg.qr(jnp.concatenate([factor, rows]), mode="r")[: p + 1]

        def chunk(carry: tuple[jax.Array, ...], at: tuple[jax.Array, ...]):
            def step(state: tuple[jax.Array, ...], at: tuple[jax.Array, ...]):
                h, y, w, *uv = at
                out, rs, Js = [], [], []
                for i, mover in enumerate(movers):
                    lo, hi = uv[2 * i], uv[2 * i + 1]
                    x, dx = mover(state[2 * i], state[2 * i + 1], self.bound, h, lo, hi)
                    out += [x, dx]
                    rs.append((x - y) * w)  # [B, S]
                    Js.append(jnp.swapaxes(dx, 1, 2) * w[:, :, None])  # [B, S, P]
                return tuple(out), (jnp.stack(rs), jnp.stack(Js))

            state, (r, J) = jax.lax.scan(step, carry[:-1], at)
            return (*state, fold(carry[-1], J, r)), None

        zeros = jnp.zeros((b, p, s), theta.dtype)
        r0 = (self.x0 - self.y[:, :, 0]) * w0  # the same for both simulations
        factor = fold(jnp.zeros((p + 1, p + 1), theta.dtype), jnp.zeros((2, b, s, p)),
                      jnp.stack([r0, r0]))  # fmt: skip
        carry = (self.x0, zeros, self.x0, zeros, factor)
        return jax.lax.scan(chunk, carry, inputs)[0][-1]

    def errors(self, theta: jax.Array) -> np.ndarray:
        """NRMSE ``[2, B, S]`` of the closed and the open rollouts (inf where one diverged);
        with time blocks, over each row's block (scaled by the whole recording's range)."""
        out = []
        for sim in self._compiled(theta):
            sim = np.asarray(sim)
            err = select._nrmse(sim, np.asarray(self.y), self.windows)
            beyond = np.abs(sim) >= np.asarray(self.bound)[:, :, None]
            if self.windows is not None:
                beyond &= select._window_mask(self.windows, sim.shape[2])[:, None, :]
            hit = np.any(beyond, axis=2)
            out.append(np.where(hit, np.inf, err))
        return np.stack(out)


def _levenberg_marquardt(
    factor: Callable[[jax.Array], jax.Array], theta0: jax.Array, max_steps: int,
    rtol: float = 1e-8, atol: float = 1e-8,
) -> tuple[jax.Array, int]:  # fmt: skip
    """The parameters that minimise ``|r(theta)|^2`` from ``theta0``, and the steps taken:
    Levenberg-Marquardt with a classical trust region (optimistix's rules: the damping
    ``lambda`` starts at 1, is divided by 3.5 after a step whose actual reduction is within
    1 % of the predicted one, and multiplied by 4 after one that achieves less than 1 %,
    which is rejected). ``factor(theta)`` is :meth:`_Simulator.factor`: each damped step
    solves ``min |R d + z|^2 + lambda |d|^2`` on it. Stops when an accepted step changes every
    parameter and the sum of squares by less than ``atol + rtol`` times their new size, or a
    rejected one changes every parameter by less than that."""
    theta = np.asarray(theta0, dtype=float)
    p = theta.size

    def split(f: jax.Array) -> tuple[np.ndarray, np.ndarray, float]:
        f = np.asarray(f)
        R, z = f[:p, :p], f[:p, p]
        return R, z, float(z @ z + f[p, p] ** 2) if np.all(np.isfinite(f)) else np.inf

    R, z, cost = split(factor(jnp.asarray(theta)))
    lam, steps = 1.0, 0
    while steps < max_steps and np.isfinite(cost):
        steps += 1
        A = np.concatenate([R, np.sqrt(lam) * np.eye(p)])
        d = np.linalg.lstsq(A, np.concatenate([-z, np.zeros(p)]), rcond=None)[0]
        predicted = float(z @ z - np.sum((R @ d + z) ** 2))
        trial = theta + d
        R_new, z_new, new = split(factor(jnp.asarray(trial)))
        ratio = (cost - new) / predicted if predicted > 0 else -np.inf
        small = np.all(np.abs(d) < atol + rtol * np.abs(trial))
        if ratio > 0.99:
            lam /= 3.5
        elif not ratio >= 0.01:
            if small:  # nothing left to gain within the tolerance
                break
            lam *= 4.0
            continue
        settled = abs(cost - new) < atol + rtol * abs(new)
        theta, R, z, cost = trial, R_new, z_new, new
        if small and settled:
            break
    return jnp.asarray(theta), steps


def refit_simulation(
    de: Equations,
    ae: Equations,
    train: Sequence[Dataset],
    played_from: Sequence[Dataset] | None = None,
    config: select.SelectionConfig | None = None,
    *,
    max_steps: int = 200,
    fold_params: bool = False,
) -> tuple[Equations, Equations, dict[str, Any]]:
    """The state and algebraic equations' parameters fitted to how the model simulates the
    training recordings, kept only if that lowers the left-out simulation error.

    ``played_from`` gives the played-in channels and the initial states (default ``train``;
    the pipeline passes the recordings with the states estimated by the model, whose first
    sample is less noisy than the measured one). ``config`` (default
    :class:`jaxdmd.select.SelectionConfig`) gives the guard's ``tolerance`` and the
    simulation's ``substeps`` and ``blowup``. The residual is that of the states simulated
    closed and with the measured algebraic variables played in, each scaled by the recording's
    range (NRMSE). A line built from products of the other algebraic lines is fitted as the
    relation it is among them (:func:`jaxdmd.select.linked`), so that it moves with them, and
    written back with them in it (:meth:`jaxdmd.select.Linked.back`). Returns the equations
    (refitted or as given) and a report: ``kept``
    (``"refit"`` or why not), what was left out (``held_out``: ``"recordings"`` or, with one
    recording, ``"time blocks (4)"``), the mean left-out NRMSE of the refit and the in-sample
    NRMSE of the given parameters on the same recordings or blocks (``loro``), the in-sample
    NRMSE before and after, and the seconds. ``fold_params``: also each left-out fold's fitted
    parameters (``report["fold_params"]``, DE then AE, one list per fold; for a jackknife).
    """
    config = config or select.SelectionConfig()
    start = time.perf_counter()
    train = list(train)
    played_from = train if played_from is None else list(played_from)
    report: dict[str, Any] = {}
    given, link = ae, select.linked(ae)
    if link is not None:  # a line built from the others moves with them
        ae = link.equations

    def done(reason: str, out: tuple[Equations, Equations] = (de, given)) -> tuple[
        Equations, Equations, dict[str, Any]
    ]:  # fmt: skip
        report["kept"] = reason
        report["seconds"] = time.perf_counter() - start
        if link is not None:  # each fold's parameters in the given equations' order
            n = len(de.params)
            for theta in folds:
                theta[n:] = link.given_params(theta[n:]).tolist()
        return out[0], out[1], report

    t0 = np.asarray(train[0].t)
    folds: list[list[float]] = []
    if any(not np.array_equal(np.asarray(ds.t), t0) for ds in [*train, *played_from]):
        return done("given: the recordings do not share a time grid")
    sim = _Simulator(de, ae, train, played_from, config.substeps, config.blowup)
    theta0 = jnp.asarray(sim.theta0)
    before = sim.errors(theta0)
    if not np.all(np.isfinite(before)):
        return done("given: the model does not simulate every training recording")

    def fit(theta: jax.Array, weight: jax.Array) -> tuple[jax.Array, int]:
        """Fitted from ``theta`` with ``weight`` per recording or per sample (one program)."""
        weight = np.asarray(weight)
        weight = weight[:, None] if weight.ndim == 1 else weight
        return _levenberg_marquardt(sim.factor(weight), theta, max_steps)

    b = len(train)
    if fold_params:
        report["fold_params"] = folds
    if b > 1:
        report["held_out"] = "recordings"
        # each recording left out: fitted on the others from the given parameters, simulated
        left_out = []
        for i in range(b):
            weight = jnp.asarray(np.arange(b) != i, dtype=theta0.dtype)
            theta, _ = fit(theta0, weight)
            folds.append([float(x) for x in np.asarray(theta)])
            err = sim.errors(theta)[:, i]
            left_out.append(float(np.mean(err)) if np.all(np.isfinite(err)) else float("inf"))
        old = float(np.mean(before))
        new = float(np.mean(left_out))
        report["loro"] = {"given": old, "refit": new, "per_recording": left_out}
    else:
        # one recording: its time blocks left out in turn (select._held_out), each fitted on
        # the other blocks' samples and simulated from the states at its first sample
        blocks = select.time_blocks(t0)
        report["held_out"] = f"time blocks ({len(blocks)})"
        k = len(blocks)
        if k < 2:
            return done("given: one recording too short to cut into time blocks")
        held = _Simulator(
            de, ae, train * k, played_from * k, config.substeps, config.blowup, windows=blocks
        )
        given = held.errors(theta0)  # [2, blocks, S], the given parameters on each block
        if not np.all(np.isfinite(given)):
            return done("given: the model does not simulate every time block")
        left_out = []
        for i, (start, stop) in enumerate(blocks):
            weight = np.ones((1, t0.size))
            weight[0, start:stop] = 0.0
            theta, _ = fit(theta0, jnp.asarray(weight, dtype=theta0.dtype))
            folds.append([float(x) for x in np.asarray(theta)])
            err = held.errors(theta)[:, i]
            left_out.append(float(np.mean(err)) if np.all(np.isfinite(err)) else float("inf"))
        old = float(np.mean(given))
        new = float(np.mean(left_out))
        report["loro"] = {"given": old, "refit": new, "per_block": left_out}
    if not new * (1.0 + config.tolerance) < old:
        return done(f"given: the refit does not simulate left-out {report['held_out']} better")
    every = jnp.ones(b if b > 1 else (1, t0.size), dtype=theta0.dtype)  # one compiled fit
    theta, steps = fit(theta0, every)
    after = sim.errors(theta)
    report["steps"] = int(steps)
    report["nrmse"] = {
        "before": {"closed": float(np.mean(before[0])), "played_in": float(np.mean(before[1]))},
        "after": {"closed": float(np.mean(after[0])), "played_in": float(np.mean(after[1]))},
    }
    theta = np.asarray(theta, dtype=float)
    if not (np.all(np.isfinite(after)) and np.all(np.isfinite(theta))):
        return done("given: the refit on every recording failed")
    if float(np.mean(after)) > float(np.mean(before)):
        return done("given: the refit on every recording simulates them worse")
    de_new = dataclasses.replace(de, params=tuple(float(x) for x in theta[: sim.n_de]))
    ae_new = dataclasses.replace(ae, params=tuple(float(x) for x in theta[sim.n_de :]))
    if link is not None:
        back = link.back(ae_new)
        if back is None:  # its constants written out longer
            return done("given: a line built from the others exceeds a skeleton's size")
        ae_new = back
    return done("refit", (de_new, ae_new))


def simulated_structure(de: Equations, ae: Equations) -> tuple[str, ...]:
    """The texts of ``ae``'s lines for the algebraic variables the state equations use, in
    order: what the simulation refit sees of an AE equation set (its residual holds only the
    states), less the parameters, which the refit fits."""
    used = select.used_variables(de)
    lines, _ = ln.split_lines(ae.source)
    return tuple(
        line.text for target, line in zip(ae.contract.targets, lines, strict=True)
        if target in used
    )  # fmt: skip


def held_out_error(report: dict[str, Any]) -> float:
    """The mean left-out simulation error of the structure in a :func:`refit_simulation`
    report, its parameters fitted to simulate the other recordings (or time blocks): how the
    structure simulates data it was not fitted to, whether or not the refit is then kept; inf
    where nothing was measured."""
    loro = report.get("loro")
    value = float(loro["refit"]) if loro else float("inf")
    return value if np.isfinite(value) else float("inf")


def refit_task(
    de: Equations, ae: Equations, train: Sequence[Dataset],
    played_from: Sequence[Dataset] | None, config: select.SelectionConfig | None, *,
    progress: Callable[[Any], None],
) -> tuple[Equations, Equations, dict[str, Any]]:  # fmt: skip
    """:func:`refit_simulation` as the task of a worker process (:mod:`jaxdmd.workers`)."""
    return refit_simulation(de, ae, train, played_from, config)


def refit_finalists(
    de: Equations,
    finalists: Sequence[tuple[str, Equations]],
    train: Sequence[Dataset],
    played_from: Sequence[Dataset] | None = None,
    config: select.SelectionConfig | None = None,
    started: Mapping[str, Callable[[], tuple[Equations, Equations, dict[str, Any]]]] | None = None,
) -> tuple[Equations, Equations, dict[str, Any]]:
    """Of several algebraic equation sets, the one whose structure simulates best once its
    parameters are fitted to simulate, judged on data they were not fitted to.

    Each finalist (name, equations), in order of preference, is refitted with the state
    equations by :func:`refit_simulation` and scored by its :func:`held_out_error`; a later
    finalist replaces the current choice only if its error is lower by more than the
    selection's ``tolerance`` (as every choice of the selection). A choice among lines whose
    parameters are fitted to equation errors cannot see how far the simulation refit will
    take each of them: a structure whose least-squares parameters simulate badly may be the
    one that simulates best once they are fitted to simulate (measured on the benchmark, IEEE
    39-bus generator 30, seed 0: the selection's lines 0.035 NRMSE left out after the refit,
    the AE loop's own choice 0.0145; on the test fault 0.79 % against 0.50 % MAPE). Returns
    the chosen finalist's equations as :func:`refit_simulation` delivers them (refitted or
    given) and its report, with ``finalists`` (per finalist its name, ``held_out_nrmse`` and
    whether its refit was kept) and ``chosen`` (the name) added. A finalist whose lines for
    the variables the state equations use have the same structure as an earlier one's (they
    differ only where no state sees it, or in their parameters, which the refit fits) is not
    refitted: there is no structure to decide between. ``started``: per finalist name, the
    result of its :func:`refit_simulation` with these ``de``, ``train``, ``played_from`` and
    ``config``, started before (in a worker process, beside other work); it is refitted here
    if that fails."""
    if not finalists:
        raise ValueError("refit_finalists needs at least one finalist")
    config = config or select.SelectionConfig()
    start = time.perf_counter()
    results, seen = [], {}
    for name, ae in finalists:
        structure = simulated_structure(de, ae)
        if structure in seen:  # the states simulate the same structure: nothing to decide
            seen_name = seen[structure]
            skipped = f"not refitted: the lines the states use are those of {seen_name!r}"
            results.append((name, de, ae, {"kept": skipped}))
            continue
        seen[structure] = name
        refitted, failed = None, None
        if started and name in started:
            try:
                refitted = started[name]()
            except workers.WorkerError as err:
                failed = str(err)
        if refitted is None:
            refitted = refit_simulation(de, ae, train, played_from, config)
        if failed is not None:
            refitted[2]["worker_failed"] = failed  # refitted here instead
        results.append((name, *refitted))
    errors = [held_out_error(r[3]) for r in results]
    best = 0
    for i in range(1, len(results)):
        if errors[i] * (1.0 + config.tolerance) < errors[best]:
            best = i
    name, de_out, ae_out, report = results[best]
    report = dict(report)
    report["finalists"] = [
        {"name": r[0], "held_out_nrmse": e, "kept": r[3]["kept"]}
        | ({"worker_failed": r[3]["worker_failed"]} if "worker_failed" in r[3] else {})
        for r, e in zip(results, errors, strict=True)
    ]
    report["chosen"] = name
    report["seconds"] = time.perf_counter() - start
    return de_out, ae_out, report
