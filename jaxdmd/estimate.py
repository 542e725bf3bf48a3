"""State estimation with a discovered model: an extended Rauch-Tung-Striebel smoother.

The AE loop regresses the algebraic variables on the states, and measured states are noisy.
A generic smoother (``jaxdmd.data.differentiate``) knows nothing of the machine: it trades noise
against the blurring of fast transients. Once the DE loop has found the state equations, they
link the states to the measured algebraic channels and inputs (d delta/dt = Omega_b (omega - 1)
ties the angle to the speed; d e''_d/dt follows i_q), and a Kalman smoother that uses them as
its process model estimates the states far better than either the measurement or a generic
smoother can. That is what this module does:

- process model: the DE equations, stepped with Heun's rule between samples, the channels that
  are not states (algebraic variables, inputs) taken as measured; an interval that ends at an
  event (fault on, clearing: the sample holds the values after the jump) is stepped with its
  left end only, as :func:`jaxdmd.problems.integral_operator` integrates it;
- measurement: every state, white noise of the variance given per state (by default estimated
  from the generic smoother's residual, :func:`jaxdmd.refine.smoothed_states`);
- process noise: white, of intensity ``(s_i * scale_i)^2`` per state, where ``scale_i`` is the
  RMS of the estimated derivative of state ``i`` and the factors ``s_i`` are chosen by maximum
  likelihood (the filter's innovations), one state at a time over a grid, two sweeps. The model
  errors of a discovered equation (a coefficient off by a percent) are what this noise absorbs;
- extended Kalman filter forward, RTS smoother backward (linearised by ``jax.jacfwd`` at the
  filtered estimate, exact for equations linear in the states), one ``lax.scan`` each.

Returns the smoothed states and their posterior covariance per sample, which the AE loop's
bias-compensated refit uses as the noise that remains in its regressors. With AE equations as
further measurement equations, :meth:`ModelSmoother.log_likelihood` is the likelihood of all
the data as a differentiable function of the AE parameters (``jaxdmd.refine.refit_joint``).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxdmd.data import Dataset, event_samples
from jaxdmd.skeleton import Skeleton

# the factors s_i tried for the process noise: (s_i * RMS of dx_i/dt)^2 per second
PROCESS_GRID = tuple(float(x) for x in np.logspace(-6.0, 0.0, 13))


@dataclass(frozen=True)
class StateEstimate:
    """A recording with its states replaced by the model-based smoothed estimates.

    ``covariance`` [n, S, S] is the posterior covariance of the states (``states`` order) per
    sample (None in a copy made by :func:`without_covariance`); ``process`` the chosen
    process-noise factor and ``noise`` the measurement-noise variance per state;
    ``log_likelihood`` of the innovations at the chosen factors.
    """

    dataset: Dataset
    states: tuple[str, ...]
    covariance: np.ndarray | None
    process: dict[str, float]
    noise: dict[str, float]
    log_likelihood: float

    @property
    def from_model(self) -> bool:
        """Estimated with a process model (:class:`ModelSmoother`), not a generic smoother."""
        return bool(self.process)


def without_covariance(estimate: StateEstimate) -> StateEstimate:
    """``estimate`` without its covariances: what is sent to work in another process that does
    not read them (the joint refits), since they are most of an estimate's size
    (``[n, S, S]`` against the recording's ``[channels, n]``: 80 of 147 MB at four recordings
    of 1e5 samples)."""
    return dataclasses.replace(estimate, covariance=None)


def _transition(rate):
    """x_{k+1} = step(x_k, u_k, u_{k+1}, h, left): Heun's rule with measured non-states; an
    interval that ends at an event (``left``) uses the values at its left end throughout."""

    def step(x, u0, u1, h, left):
        k0 = rate(x, u0)
        u_end = jax.tree.map(lambda a, b: jnp.where(left, a, b), u0, u1)
        k1 = rate(x + h * k0, u_end)
        return x + 0.5 * h * (k0 + k1)

    return step


def _filter_steps(step, observe, q, r):
    """The EKF's measurement update ``update(m, p, y_k, u_k) -> (m, p, log-likelihood)`` and its
    step between samples ``forward((m, p), inputs) -> ((m, p), (m, p, m_pred, p_pred, A, ll))``
    (the prediction by ``step``, linearised by ``jax.jacfwd``, then the update)."""
    n_states = q.shape[0]
    eye = jnp.eye(n_states)
    rmat = jnp.diag(r)

    def update(m, p, yk, uk):
        hx = jax.jacfwd(observe)(m, uk)  # [O, S]
        s = hx @ p @ hx.T + rmat
        chol = jax.scipy.linalg.cho_factor(s)
        gain = jax.scipy.linalg.cho_solve(chol, hx @ p).T  # P H' S^-1
        v = yk - observe(m, uk)
        ikh = eye - gain @ hx
        p_new = ikh @ p @ ikh.T + gain @ rmat @ gain.T  # Joseph form
        ll = -0.5 * (
            v @ jax.scipy.linalg.cho_solve(chol, v)
            + 2.0 * jnp.sum(jnp.log(jnp.diag(chol[0])))
            + v.shape[0] * jnp.log(2 * jnp.pi)
        )
        return m + gain @ v, p_new, ll

    def forward(carry, inp):
        m, p = carry
        yk, u0, u1, hk, lk = inp
        a = jax.jacfwd(step)(m, u0, u1, hk, lk)
        m_pred = step(m, u0, u1, hk, lk)
        p_pred = a @ p @ a.T + jnp.diag(q * hk)
        m_new, p_new, ll = update(m_pred, p_pred, yk, u1)
        return (m_new, p_new), (m_new, p_new, m_pred, p_pred, a, ll)

    return update, forward


def _filter_smoother(step, observe, x0, p0, y, u, h, left, q, r):
    """EKF forward and RTS backward; returns smoothed means [n, S], covariances [n, S, S] and
    the innovations' log-likelihood. ``observe(x, u_k)`` gives the measured vector y_k [O]
    (the states themselves, or more); ``q`` [S] process-noise intensity, ``r`` [O] noise."""
    update, forward = _filter_steps(step, observe, q, r)
    m0, pm0, ll0 = update(x0, p0, y[0], jax.tree.map(lambda v: v[0], u))
    u_prev = jax.tree.map(lambda v: v[:-1], u)
    u_next = jax.tree.map(lambda v: v[1:], u)
    _, (ms, ps, m_preds, p_preds, jac, lls) = jax.lax.scan(
        forward, (m0, pm0), (y[1:], u_prev, u_next, h, left)
    )
    ms = jnp.concatenate([m0[None], ms])
    ps = jnp.concatenate([pm0[None], ps])

    def backward(carry, inp):
        ms_next, ps_next = carry
        m, p, m_pred, p_pred, a = inp
        g = jnp.linalg.solve(p_pred.T, (p @ a.T).T).T  # P A' P_pred^-1
        m_s = m + g @ (ms_next - m_pred)
        p_s = p + g @ (ps_next - p_pred) @ g.T
        p_s = 0.5 * (p_s + p_s.T)
        return (m_s, p_s), (m_s, p_s)

    _, (m_s, p_s) = jax.lax.scan(
        backward, (ms[-1], ps[-1]), (ms[:-1], ps[:-1], m_preds, p_preds, jac), reverse=True
    )
    m_s = jnp.concatenate([m_s, ms[-1:]])
    p_s = jnp.concatenate([p_s, ps[-1:]])
    return m_s, p_s, ll0 + jnp.sum(lls)


def _log_likelihood(step, observe, x0, p0, y, u, h, left, q, r):
    """The innovations' log-likelihood of the EKF of :func:`_filter_smoother` (the same
    operations), without the smoother and without keeping the filter's path: differentiated,
    each step is computed again in the backward pass (``jax.checkpoint``) instead of keeping its
    intermediate values for every sample, so the gradient's memory is the filter's state per
    sample (the joint refit's own memory at four recordings of 1e5 samples: about 4.3 GB
    before, 0.5 GB after, 0.18 GB with the recordings an argument of the compiled likelihood,
    :attr:`ModelSmoother.recordings`; docs/benchmarks.md)."""
    update, forward = _filter_steps(step, observe, q, r)
    m0, pm0, ll0 = update(x0, p0, y[0], jax.tree.map(lambda v: v[0], u))

    @jax.checkpoint
    def filtered(carry, inp):
        carry, out = forward(carry, inp)
        return carry, out[-1]

    u_prev = jax.tree.map(lambda v: v[:-1], u)
    u_next = jax.tree.map(lambda v: v[1:], u)
    _, lls = jax.lax.scan(filtered, (m0, pm0), (y[1:], u_prev, u_next, h, left))
    return ll0 + jnp.sum(lls)


def _identity(x, u):
    return x


def _call(fn, params, names, states):
    """f(x, u) -> stacked outputs, the states taken from the vector x, the rest from u."""
    index = {s: i for i, s in enumerate(states)}

    def call(x, u):
        args = [x[index[a]] if a in index else u[a] for a in names]
        return jnp.stack([jnp.asarray(o, dtype=x.dtype) for o in fn(*args, params)])

    return call


class ModelSmoother:
    """The Kalman smoother of some recordings with the state equations as process model,
    prepared once: the data as arrays, the filter compiled once, the process noise chosen.

    ``de`` is the DE loop's compiled skeleton (outputs: the derivatives of ``states`` in order)
    and ``de_params`` its parameters; ``noise`` the measurement-noise variance of each state, per
    recording (floored at 1e-12 of the state's variance, so that a clean state still gives a
    regular filter). With ``ae`` (a compiled AE skeleton of the ``targets``), the algebraic
    variables are measurements too, through the AE equations, whose parameters and error
    variances are given to :meth:`log_likelihood` (which :func:`jaxdmd.refine.refit_joint`
    maximises); :meth:`smooth` estimates the states from their own measurements.
    The process-noise factors are chosen per state by maximum likelihood over all recordings
    (:data:`PROCESS_GRID`, coordinate-wise, ``sweeps`` passes) without the AE equations, unless
    ``process`` gives them (as a smoother of the same recordings chose them).
    """

    def __init__(
        self,
        de: Skeleton,
        de_params: Sequence[float],
        states: Sequence[str],
        datasets: Sequence[Dataset],
        noise: Sequence[Mapping[str, float]],
        *,
        ae: Skeleton | None = None,
        targets: Sequence[str] = (),
        grid: Sequence[float] = PROCESS_GRID,
        sweeps: int = 2,
        process: Mapping[str, float] | None = None,
    ) -> None:
        self.states = states = tuple(states)
        self.targets = tuple(targets) if ae is not None else ()
        self.datasets = list(datasets)
        self.noise = [{s: float(v[s]) for s in states} for v in noise]
        n_states = len(states)
        names = set(de.arguments) | (set(ae.arguments) if ae is not None else set())
        others = tuple(sorted(names - set(states)))
        prepared, rates = [], []
        for ds, var in zip(self.datasets, self.noise, strict=True):
            t = np.asarray(ds.t, dtype=float)
            y = np.stack([np.asarray(ds[s], dtype=float) for s in (*states, *self.targets)], 1)
            u = {a: jnp.asarray(np.asarray(ds[a], dtype=float)) for a in others}
            left = jnp.asarray(event_samples(t, ds.events)[1:])
            floor = 1e-12 * np.var(y[:, :n_states], axis=0) + 1e-300
            r = np.maximum([var[s] for s in states], floor)
            prepared.append((jnp.asarray(y), u, jnp.asarray(np.diff(t)), left, r))
            estimated = ds.with_estimated_derivatives()
            rates.append(np.stack([estimated.derivative(s) for s in states], axis=1))
        scale = np.sqrt(np.mean(np.concatenate(rates) ** 2, axis=0)) + 1e-300
        # the recordings are held once, stacked by length: recording k is row where[k][1] of
        # batch where[k][0]
        self._where: list[tuple[int, int]] = [(0, 0)] * len(prepared)
        self._batches = []
        for b, n in enumerate(sorted({int(d[0].shape[0]) for d in prepared})):
            members = [k for k, d in enumerate(prepared) if d[0].shape[0] == n]
            for row, k in enumerate(members):
                self._where[k] = (b, row)
            self._batches.append(
                jax.tree.map(
                    lambda *a: jnp.stack([jnp.asarray(x) for x in a]),
                    *[prepared[k] for k in members],
                )
            )
        del prepared
        de_p = jnp.asarray(de_params, dtype=jnp.float64)
        step = _transition(_call(de.fn, de_p, de.arguments, states))

        def run_states(q, r, y, u, h, left):
            return _filter_smoother(step, _identity, y[0], jnp.diag(r), y, u, h, left, q, r)

        def observer(ae_p):
            relation = _call(ae.fn, ae_p, ae.arguments, states)

            def observe(x, uk):
                return jnp.concatenate([x, relation(x, uk)])

            return observe

        def run_joint(ae_p, q, r, y, u, h, left):
            x0 = y[0, :n_states]
            return _log_likelihood(
                step, observer(ae_p), x0, jnp.diag(r[:n_states]), y, u, h, left, q, r
            )

        def run_smoother(ae_p, q, r, y, u, h, left):
            x0 = y[0, :n_states]
            return _filter_smoother(
                step, observer(ae_p), x0, jnp.diag(r[:n_states]), y, u, h, left, q, r
            )

        self._run_states = jax.jit(run_states)
        self._run_joint = run_joint
        self._run_smoother = jax.jit(run_smoother)
        states_only = jax.jit(
            jax.vmap(lambda *a: run_states(*a)[2], in_axes=(0, None, None, None, None, None))
        )
        if process is not None:  # chosen before (by a smoother of the same recordings)
            factors = np.array([float(process[s]) for s in states])
        else:
            factors = np.full(n_states, grid[len(grid) // 2])
        grid_arr = np.asarray(grid)
        for _ in range(0 if process is not None else sweeps):
            for i in range(n_states):
                trial = np.repeat(factors[None], len(grid_arr), axis=0)
                trial[:, i] = grid_arr
                q = jnp.asarray((trial * scale) ** 2)
                total = sum(
                    np.asarray(states_only(q, jnp.asarray(r), y[:, :n_states], u, h, left))
                    for y, u, h, left, r in map(self._recording, range(len(self.datasets)))
                )
                total = np.where(np.isfinite(total), total, -np.inf)
                factors[i] = grid_arr[int(np.argmax(total))]
        self.process = dict(zip(states, factors.tolist(), strict=True))
        self._q = jnp.asarray((factors * scale) ** 2)

    def _recording(self, k: int) -> tuple[Any, ...]:
        """Recording ``k`` as arrays: its measurements, inputs, steps, event flags and noise."""
        batch, row = self._where[k]
        return jax.tree.map(lambda v: v[row], self._batches[batch])

    @property
    def recordings(self) -> list[tuple[Any, ...]]:
        """The recordings as arrays (a pytree), one batch per recording length: what
        :meth:`log_likelihood` takes as ``recordings`` inside a compiled function, so that they
        enter it as an argument rather than as constants copied into every compiled program."""
        return self._batches

    def log_likelihood(
        self, ae_params: jax.Array, ae_variance: jax.Array, recordings: Any = None
    ) -> jax.Array:
        """The log-likelihood of all recordings (the filter's innovations) with the AE equations
        at ``ae_params`` and error variances ``ae_variance``: traceable, differentiable.
        ``recordings``: :attr:`recordings` (the default), passed in by a caller that compiles."""
        total = jnp.zeros(())
        for y, u, h, left, r in self._batches if recordings is None else recordings:
            # recordings of one length: one vmapped scan
            rr = jnp.concatenate(
                [r, jnp.broadcast_to(ae_variance, (r.shape[0], *ae_variance.shape))], axis=1
            )
            ll = jax.vmap(lambda *a: self._run_joint(ae_params, self._q, *a))(rr, y, u, h, left)
            total = total + jnp.sum(ll)
        return total

    def smooth(
        self, ae_params: Sequence[float] | None = None, ae_variance: Sequence[float] | None = None
    ) -> list[StateEstimate]:
        """The smoothed states of every recording: from the states' own measurements, or with
        ``ae_params`` and ``ae_variance`` (a smoother built with ``ae``) from the algebraic
        measurements too, through the AE equations with those parameters and error variances."""
        n_states = len(self.states)
        out = []
        for k, (ds, var) in enumerate(zip(self.datasets, self.noise, strict=True)):
            y, u, h, left, r = self._recording(k)
            if ae_params is None or not self.targets:
                m, cov, ll = self._run_states(self._q, jnp.asarray(r), y[:, :n_states], u, h, left)
            else:
                rr = jnp.concatenate([r, jnp.asarray(ae_variance, dtype=r.dtype)])
                m, cov, ll = self._run_smoother(
                    jnp.asarray(ae_params, dtype=jnp.float64), self._q, rr, y, u, h, left
                )
            values = {s: np.asarray(m[:, j]) for j, s in enumerate(self.states)}
            out.append(
                StateEstimate(
                    dataset=ds.with_values(values),
                    states=self.states,
                    covariance=np.asarray(cov),
                    process=dict(self.process),
                    noise=dict(var),
                    log_likelihood=float(ll),
                )
            )
        return out


def model_smoother(
    skeleton: Skeleton,
    params: Sequence[float],
    states: Sequence[str],
    datasets: Sequence[Dataset],
    noise: Sequence[Mapping[str, float]],
    *,
    grid: Sequence[float] = PROCESS_GRID,
    sweeps: int = 2,
) -> list[StateEstimate]:
    """The states of each recording smoothed with the state equations as process model (see
    :class:`ModelSmoother`, without algebraic measurements)."""
    smoother = ModelSmoother(skeleton, params, states, datasets, noise, grid=grid, sweeps=sweeps)
    return smoother.smooth()


__all__ = [
    "PROCESS_GRID",
    "ModelSmoother",
    "StateEstimate",
    "model_smoother",
    "without_covariance",
]
