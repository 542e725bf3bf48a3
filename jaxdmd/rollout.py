"""Simulating a discovered (or user-given) model with diffrax, and scoring the simulation.

A model is one block of state equations (the DE loop's `Equations`) and, optionally, blocks of
algebraic equations (the AE loop's). `rollout` integrates the state equations from the measured
initial state, with every variable the equations need but do not produce *played in* from the
recording:

- ``mode="dae"``: the algebraic variables are computed by the AE equations at every instant from
  the simulated states, the inputs (P_m, v_f) and the boundary signals (V, theta); only inputs
  and boundary signals are played in. This is the paper's closed-loop test.
- ``mode="de"``: the measured algebraic variables are played in as well (an open-loop test of
  the state equations alone; the SINDy baselines, which have no AE loop, are rolled out so).

Play-in without smearing the fault. The recorded signals jump at the events (fault on, fault
clear) between two samples. The played-in signal is the linear interpolant of the samples *of the
same segment* between two events, extended linearly up to the events, so that it is exactly
piecewise linear with jumps at the events (`play_in_knots`). A sample lying exactly on an event
belongs to the *later* segment (right-continuous signals), as the benchmark simulator and
`jaxdmd.data.segments` record it; the left limit at the event is extrapolated from the last two
samples before it. The solver is told the kinks (the sample times, ``step_ts``) and the jumps (the
events, ``jump_ts``) through `diffrax.ClipStepSizeController`: it steps to just before an event
and restarts just after it, so the vector field never straddles a jump.

The compiled solve depends only on the model's *structure* (the skeleton sources, the variable
names, the solver settings); parameters and data are traced arguments, so rolling a refitted
model or another recording out reuses the compiled code (`rollout` keeps a small cache).

A rollout never raises because the model misbehaves: a trajectory that leaves the ``blowup``
bound, turns non-finite or exhausts the step budget is returned flagged ``diverged`` with the
time it happened (`RolloutResult`), the samples after that time being NaN.

Metrics (`metrics`, `score`; definitions in ``docs/metrics.md``): MAPE with a per-signal floor
(range of the measured signal), plain MAPE where the signal stays away from zero, R^2, NRMSE and
NMAE (RMSE and mean absolute error over the range), over the whole record and over the fault
window (first event to last event + 1 s). `score` also flags a rollout ``far_off`` when it
diverged or when a state's R^2 over the whole record is below ``FAR_OFF_R2`` (-10): a rollout
that stays bounded but is far off, which ``diverged`` does not catch.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal, Protocol

import diffrax as dfx
import jax
import jax.numpy as jnp
import numpy as np

from jaxdmd.data import Dataset

__all__ = [
    "FAR_OFF_R2",
    "METRICS",
    "Block",
    "RolloutConfig",
    "RolloutResult",
    "algebraic_r2",
    "as_block",
    "at_equilibrium",
    "fault_window",
    "interpolate",
    "metrics",
    "modes",
    "play_in_knots",
    "r2",
    "rollout",
    "score",
]

Mode = Literal["dae", "de"]
METRICS: tuple[str, ...] = ("mape", "mape_plain", "r2", "nrmse", "nmae")
"""Keys of the per-state and mean metrics returned by `metrics`."""

FAR_OFF_R2 = -10.0
"""R^2 (over the whole record) below which `score` flags a state's rollout ``far_off``: its
squared error is more than eleven times the signal's variance about its mean."""


# ------------------------------------------------------------------------------------------------
# models
# ------------------------------------------------------------------------------------------------


class _EquationsLike(Protocol):
    """What `as_block` needs of a loop result (`jaxdmd.search.Equations`)."""

    source: str
    params: Sequence[float]

    @property
    def contract(self) -> Any: ...

    def skeleton(self) -> Any: ...


@dataclass(frozen=True)
class Block:
    """Explicit equations ``targets = fn(*arguments, params)``, the unit `rollout` simulates.

    ``fn`` takes one array per name in ``arguments`` (scalars inside the vector field, or [n]
    arrays) and the parameter vector, and returns a tuple with one array per target. For a state
    block the outputs are the time derivatives of the targets; for an algebraic block, the values
    of the targets. ``key`` identifies the *structure* (e.g. the skeleton source): two blocks with
    equal ``key``, targets and arguments must compute the same function for any ``params``, since
    compiled rollouts are cached on it. An empty key is replaced by one naming ``fn``'s identity.
    """

    targets: tuple[str, ...]
    arguments: tuple[str, ...]
    fn: Callable[..., tuple[Any, ...]] = field(compare=False, repr=False)
    params: np.ndarray = field(compare=False, repr=False, default_factory=lambda: np.zeros(0))
    key: str = ""

    def __post_init__(self) -> None:
        object.__setattr__(self, "targets", tuple(self.targets))
        object.__setattr__(self, "arguments", tuple(self.arguments))
        object.__setattr__(self, "params", np.asarray(self.params, dtype=np.float64).ravel())
        if not self.key:
            fn = self.fn
            name = f"{getattr(fn, '__module__', '')}.{getattr(fn, '__qualname__', repr(fn))}"
            object.__setattr__(self, "key", f"{name}@{id(fn)}")
        if len(set(self.targets)) != len(self.targets):
            raise ValueError(f"a block's targets must be distinct, got {self.targets}")

    def __call__(self, variables: Mapping[str, Any]) -> dict[str, jax.Array]:
        """Evaluate on named variables; returns target name -> array."""
        out = self.fn(*(variables[a] for a in self.arguments), jnp.asarray(self.params))
        return dict(zip(self.targets, out, strict=True))


def as_block(model: Block | _EquationsLike) -> Block:
    """A `Block` from a `Block` or a loop result (``jaxdmd.search.Equations``).

    The skeleton's ``arguments`` are the variables it uses; its outputs are the contract's
    targets in order (d/dt of the states for a DE result, the algebraic variables for an AE one).
    """
    if isinstance(model, Block):
        return model
    skeleton = model.skeleton()
    targets = tuple(model.contract.targets)
    if skeleton.n_outputs != len(targets):
        raise ValueError(
            f"the skeleton returns {skeleton.n_outputs} values but the contract has "
            f"{len(targets)} targets {targets}"
        )
    return Block(
        targets=targets,
        arguments=tuple(skeleton.arguments),
        fn=skeleton.fn,
        params=np.asarray(model.params, dtype=np.float64),
        key=f"skeleton:{skeleton.source}",
    )


# ------------------------------------------------------------------------------------------------
# play-in of recorded signals
# ------------------------------------------------------------------------------------------------


def _extrapolate(ts: np.ndarray, ys: np.ndarray, at: float, end: Literal["left", "right"]) -> Any:
    """Linear extrapolation of a segment's samples to ``at`` from its two end samples."""
    if ts.shape[0] == 1:
        return ys[0]
    if end == "left":  # extend the segment's start backwards
        (t0, t1), (y0, y1) = ts[:2], ys[:2]
    else:  # extend the segment's end forwards
        (t0, t1), (y0, y1) = ts[-2:], ys[-2:]
    return y0 + (y1 - y0) * (at - t0) / (t1 - t0)


def _continuous(data: Dataset, name: str) -> np.ndarray:
    """A recorded channel as a continuous signal: angles (unit ``rad``) are unwrapped.

    Recorders and PMU exports wrap phase angles to (-pi, pi]; interpolating across a wrap would
    sweep the played-in angle through a full turn between two samples.
    """
    values = np.asarray(data[name], dtype=np.float64)
    return np.unwrap(values) if data.unit(name) == "rad" else values


def play_in_knots(
    t: np.ndarray, values: np.ndarray, events: Sequence[float] = ()
) -> tuple[np.ndarray, np.ndarray]:
    """Knots of the piecewise-linear play-in interpolant, with jumps at the events.

    Args:
        t: sample times [n].
        values: samples [n, k] (one column per signal).
        events: discontinuity times; those outside ``(t[0], t[-1])`` are ignored.

    Returns:
        ``(T, Y)``: knot times [m] (non-decreasing; every event appears twice) and values
        [m, k]. Within the segment between two events the knots are the segment's samples; at an
        event ``e`` two knots carry the left limit (the last two samples before ``e``,
        extrapolated linearly to ``e``) and the right limit (the sample at ``e`` if there is one,
        which therefore belongs to the later segment, or the first two samples after ``e``
        extrapolated back to ``e``). `interpolate` of these knots is right-continuous.
    """
    t = np.asarray(t, dtype=np.float64)
    y = np.asarray(values, dtype=np.float64)
    if y.ndim == 1:
        y = y[:, None]
    tol = 1e-9 * max(float(np.median(np.diff(t))), 1e-300)
    evs = sorted(float(e) for e in events if t[0] + tol < float(e) < t[-1] - tol)
    # segment boundaries: a sample within tol of an event starts the later segment
    cuts = [0, *(int(np.searchsorted(t, e - tol, side="left")) for e in evs), t.shape[0]]
    T: list[np.ndarray] = []
    Y: list[np.ndarray] = []
    for k in range(len(cuts) - 1):
        a, b = cuts[k], cuts[k + 1]
        ts, ys = t[a:b], y[a:b]
        if ts.shape[0] == 0:  # two events with no sample between them: hold the next sample
            ts, ys = t[b : b + 1], y[b : b + 1]
        if k > 0:  # right limit at the event opening this segment
            e = evs[k - 1]
            if abs(ts[0] - e) > tol:
                T.append(np.array([e]))
                Y.append(np.asarray(_extrapolate(ts, ys, e, "left"))[None, :])
            else:
                ts = np.concatenate([[e], ts[1:]])
        T.append(ts)
        Y.append(ys)
        if k < len(evs):  # left limit at the event closing this segment
            e = evs[k]
            T.append(np.array([e]))
            Y.append(np.asarray(_extrapolate(ts, ys, e, "right"))[None, :])
    return np.concatenate(T), np.concatenate(Y, axis=0)


def interpolate(T: jax.Array, Y: jax.Array, s: jax.Array) -> jax.Array:
    """Evaluate the knots of `play_in_knots` at time ``s`` (scalar): returns [k].

    Right-continuous at duplicated knots (jumps); linear extrapolation beyond the ends.
    """
    m = T.shape[0]
    i = jnp.clip(jnp.searchsorted(T, s, side="right") - 1, 0, m - 2)
    t0, t1 = T[i], T[i + 1]
    w = (s - t0) / jnp.where(t1 > t0, t1 - t0, 1.0)
    return Y[i] + w * (Y[i + 1] - Y[i])


# ------------------------------------------------------------------------------------------------
# the rollout
# ------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class RolloutConfig:
    """Integration settings (static: part of the compiled rollout's cache key).

    ``solver`` is ``"tsit5"`` (explicit, fast; the default) or ``"kvaerno5"`` (implicit, for
    stiff models, e.g. small time constants such as T''_q0 = 0.04 s with large steps).
    ``blowup``: a state whose magnitude exceeds ``blowup * (1 + max |measured state|)`` counts as
    diverged. ``max_steps`` bounds the work of one rollout (accepted and rejected steps).
    """

    solver: Literal["tsit5", "kvaerno5"] = "tsit5"
    rtol: float = 1e-8
    atol: float = 1e-8
    max_steps: int = 50_000
    blowup: float = 1e3


@dataclass(frozen=True)
class RolloutResult:
    """A simulated recording on the measured sample times.

    Attributes:
        t: sample times [n] (the measured ones).
        states: simulated state name -> values [n] (NaN after a divergence).
        algebraic: algebraic variables computed by the AE blocks on the simulated states
            (``mode="dae"``; empty for ``"de"``) -> values [n].
        mode: ``"dae"`` or ``"de"``.
        played_in: the recorded channels the rollout played in.
        diverged: the trajectory blew up, turned non-finite or the solver gave up.
        diverged_at: the time of the first bad sample (None if not diverged).
        status: ``"ok"`` or what went wrong.
        n_steps: accepted solver steps.
    """

    t: np.ndarray
    states: dict[str, np.ndarray]
    algebraic: dict[str, np.ndarray]
    mode: str
    played_in: tuple[str, ...]
    diverged: bool
    diverged_at: float | None
    status: str
    n_steps: int

    def __getitem__(self, name: str) -> np.ndarray:
        if name in self.states:
            return self.states[name]
        if name in self.algebraic:
            return self.algebraic[name]
        raise KeyError(f"no simulated channel {name!r}; have {[*self.states, *self.algebraic]}")

    def __contains__(self, name: object) -> bool:
        return name in self.states or name in self.algebraic


def _solver(name: str) -> dfx.AbstractSolver:
    if name == "tsit5":
        return dfx.Tsit5()
    if name == "kvaerno5":
        return dfx.Kvaerno5()
    raise ValueError(f"unknown solver {name!r}; use 'tsit5' or 'kvaerno5'")


def _environment(
    x: jax.Array,
    u: jax.Array,
    states: tuple[str, ...],
    played: tuple[str, ...],
    ae: tuple[Block, ...],
    ae_params: tuple[jax.Array, ...],
) -> dict[str, jax.Array]:
    """All variables at one instant: states, played-in signals, then the AE blocks in order."""
    env = {n: x[..., i] for i, n in enumerate(states)}
    env.update({n: u[..., j] for j, n in enumerate(played)})
    for block, p in zip(ae, ae_params, strict=True):
        out = block.fn(*(env[a] for a in block.arguments), p)
        env.update(zip(block.targets, out, strict=True))
    return env


def _rates(
    de: Block,
    x: jax.Array,
    u: jax.Array,
    played: tuple[str, ...],
    ae: tuple[Block, ...],
    de_p: jax.Array,
    ae_p: tuple[jax.Array, ...],
) -> tuple[jax.Array, dict[str, jax.Array]]:
    """The state derivatives ``[S]`` at states ``x`` and played-in values ``u`` (the algebraic
    variables computed by ``ae`` first), and the environment they were computed in."""
    env = _environment(x, u, de.targets, played, ae, ae_p)
    dx = de.fn(*(env[a] for a in de.arguments), de_p)
    return jnp.stack([jnp.asarray(d, dtype=x.dtype) for d in dx]), env


@functools.lru_cache(maxsize=64)
def _compiled(
    de: Block,
    ae: tuple[Block, ...],
    played: tuple[str, ...],
    has_jumps: bool,
    config: RolloutConfig,
) -> Callable[..., Any]:
    """The jitted solve for one model structure (cached: blocks compare by key and names)."""
    states = de.targets
    solver = _solver(config.solver)

    def field_(s: jax.Array, x: jax.Array, args: Any) -> jax.Array:
        de_p, ae_p, T, Y, _ = args
        return _rates(de, x, interpolate(T, Y, s), played, ae, de_p, ae_p)[0]

    def blew_up(s: jax.Array, x: jax.Array, args: Any, **kwargs: Any) -> jax.Array:
        bound = args[4]
        return jnp.any(~jnp.isfinite(x)) | jnp.any(jnp.abs(x) > bound)

    def algebraic(xs: jax.Array, ts: jax.Array, args: Any) -> dict[str, jax.Array]:
        _, ae_p, T, Y, _ = args
        us = jax.vmap(lambda s: interpolate(T, Y, s))(ts)
        env = _environment(xs, us, states, played, ae, ae_p)
        return {n: jnp.broadcast_to(env[n], ts.shape) for b in ae for n in b.targets}

    @jax.jit
    def run(
        y0: jax.Array, ts: jax.Array, step_ts: jax.Array, jump_ts: jax.Array | None, args: Any
    ) -> tuple[jax.Array, dict[str, jax.Array], jax.Array, jax.Array]:
        controller = dfx.ClipStepSizeController(
            dfx.PIDController(rtol=config.rtol, atol=config.atol),
            step_ts=step_ts,
            jump_ts=jump_ts if has_jumps else None,
        )
        sol = dfx.diffeqsolve(
            dfx.ODETerm(field_),
            solver,
            t0=ts[0],
            t1=ts[-1],
            dt0=None,
            y0=y0,
            args=args,
            saveat=dfx.SaveAt(ts=ts),
            stepsize_controller=controller,
            event=dfx.Event(blew_up),
            max_steps=config.max_steps,
            throw=False,
        )
        ys = sol.ys
        # a NaN anywhere in the algebraic evaluation must not poison the states
        alg = algebraic(jnp.where(jnp.isfinite(ys), ys, 0.0), ts, args)
        failed = sol.result != dfx.RESULTS.successful
        return ys, alg, failed, sol.stats["num_accepted_steps"]

    return run


def _prepare(
    de: Block, ae: tuple[Block, ...], data: Dataset, mode: Mode
) -> tuple[tuple[str, ...], str | None]:
    """The channels to play in, checking that every variable the model needs is available."""
    states = de.targets
    produced = set(states)
    needed: list[str] = []
    for block in (*ae, de):
        for a in block.arguments:
            if a not in produced and a not in needed:
                needed.append(a)
        if block is not de:
            produced.update(block.targets)
    for s in states:
        if s not in data:
            raise ValueError(f"state {s!r} of the model is not in the data {data.label!r}")
    playable = (
        set(data.names)
        if mode == "de"
        else {n for n in data.names if data.role(n) in ("input", "boundary", "state")}
    )
    missing = [n for n in needed if n not in playable]
    if missing:
        hint = (
            " (algebraic variables must come from AE equations in mode='dae'; give ae=... or "
            "use mode='de' to play the measured ones in)"
            if mode == "dae" and all(n in data for n in missing)
            else ""
        )
        raise ValueError(f"the model needs {missing}, which the rollout cannot supply{hint}")
    return tuple(needed), None


def _ae_blocks(
    ae: Block | _EquationsLike | Sequence[Block | _EquationsLike] | None,
) -> tuple[Block, ...]:
    """The algebraic equations as blocks, evaluated in order: none, one, or several."""
    if ae is None:
        return ()
    if isinstance(ae, Block) or hasattr(ae, "skeleton"):
        return (as_block(ae),)  # type: ignore[arg-type]
    return tuple(as_block(a) for a in ae)  # type: ignore[union-attr]


def rollout(
    de: Block | _EquationsLike,
    data: Dataset,
    *,
    ae: Block | _EquationsLike | Sequence[Block | _EquationsLike] | None = None,
    mode: Mode = "dae",
    config: RolloutConfig | None = None,
) -> RolloutResult:
    """Simulate the state equations from the measured initial state, on ``data.t``.

    Args:
        de: the state equations (a DE loop's `Equations`, or a `Block`); its targets are the
            simulated states, their initial values are the first measured samples.
        data: the recording supplying the initial state and the played-in signals.
        ae: the algebraic equations (an AE loop's `Equations`, a `Block`, or several, evaluated
            in order so that a later block may use an earlier one's outputs). Used in both modes;
            in ``"de"`` mode they only override measured channels of the same name.
        mode: ``"dae"``: the algebraic variables the state equations need come from ``ae``; only
            inputs, boundary signals (and states the DE block does not simulate) are played in.
            ``"de"``: any recorded channel the equations use is played in.
        config: solver settings (`RolloutConfig`).

    Returns:
        A `RolloutResult`; a divergence is flagged in it, never raised.

    Raises:
        ValueError: if the model needs a variable the rollout cannot supply (a set-up error, not
            a property of the model's dynamics).
    """
    if mode not in ("dae", "de"):
        raise ValueError(f"unknown mode {mode!r}; use 'dae' or 'de'")
    config = config or RolloutConfig()
    de_b = as_block(de)
    ae_list = _ae_blocks(ae)
    played, _ = _prepare(de_b, ae_list, data, mode)
    states = de_b.targets

    t = np.asarray(data.t, dtype=np.float64)
    cols = (
        np.stack([_continuous(data, n) for n in played], axis=1)
        if played
        else np.zeros((t.shape[0], 1))
    )
    T, Y = play_in_knots(t, cols, data.events)
    jumps = np.asarray(sorted({float(e) for e in T[1:][np.diff(T) == 0]}), dtype=np.float64)
    step_ts = t[~np.isin(t, jumps)]
    x_meas = np.stack([np.asarray(data[s]) for s in states], axis=1)
    y0 = x_meas[0]
    bound = config.blowup * (1.0 + np.max(np.abs(x_meas), axis=0))
    run = _compiled(de_b, ae_list, played, bool(jumps.size), config)
    args = (
        jnp.asarray(de_b.params),
        tuple(jnp.asarray(b.params) for b in ae_list),
        jnp.asarray(T),
        jnp.asarray(Y),
        jnp.asarray(bound),
    )
    ys, alg, failed, n_steps = run(
        jnp.asarray(y0),
        jnp.asarray(t),
        jnp.asarray(step_ts),
        jnp.asarray(jumps) if jumps.size else None,
        args,
    )
    ys = np.array(ys, dtype=np.float64)
    bad = ~np.all(np.isfinite(ys) & (np.abs(ys) <= bound), axis=1)
    failed = bool(failed)
    diverged = bool(bad.any()) or failed
    if bad.any():
        first = int(np.argmax(bad))
        at: float | None = float(t[first])
        status = "diverged: states left the blow-up bound or turned non-finite"
    elif failed:
        first, at = t.shape[0], float(t[-1])
        status = "diverged: the solver failed (step budget exhausted or step size collapsed)"
    else:
        first, at, status = t.shape[0], None, "ok"
    ys[first:] = np.nan
    alg_np = {n: np.asarray(v, dtype=np.float64).copy() for n, v in alg.items()}
    for v in alg_np.values():
        v[first:] = np.nan
    shown_alg = alg_np if mode == "dae" or ae_list else {}
    return RolloutResult(
        t=t,
        states={s: ys[:, i] for i, s in enumerate(states)},
        algebraic=shown_alg,
        mode=mode,
        played_in=played,
        diverged=diverged,
        diverged_at=at,
        status=status,
        n_steps=int(n_steps),
    )


def modes(
    de: Block | _EquationsLike,
    data: Dataset,
    *,
    ae: Block | _EquationsLike | Sequence[Block | _EquationsLike] | None = None,
    mode: Mode = "dae",
    at: int = 0,
) -> dict[str, Any]:
    """The model's small-signal modes at the operating point of ``data``'s sample ``at``
    (default the first: a recording's pre-disturbance steady state): the eigenvalues of the
    Jacobian of the state derivatives with respect to the states there, the algebraic
    variables closed by ``ae`` (``mode="dae"``; with ``"de"`` they are played in as recorded and
    held), the inputs and the boundary held at their recorded values.

    Returns ``eigenvalues`` (``[re, im]`` in 1/s, sorted by real part, largest first),
    ``max_real`` (the largest real part: above zero the linearised model is unstable),
    ``oscillatory``: per complex pair (``im > 0``) its ``frequency_hz`` and ``damping_ratio``
    (-re/|lambda|), and ``rates``: each state's derivative there times the recording's duration
    over the state's range (near zero where the model's equations vanish at a recorded steady
    state; of order one or more where the model would drift off it).

    With the boundary (terminal voltage and angle) held, these are the modes of the machine on
    an infinitely stiff bus, not of the machine in its network: a machine whose recordings are
    stable can be unstable here (the benchmark's generator 30, x'_q < x'_d: +0.48 /s)."""
    de_b = as_block(de)
    ae_list = _ae_blocks(ae)
    played, _ = _prepare(de_b, ae_list, data, mode)
    states = de_b.targets
    x0 = jnp.asarray([float(np.asarray(data[n])[at]) for n in states])
    u0 = jnp.asarray([float(np.asarray(data[n])[at]) for n in played])
    de_p = jnp.asarray(de_b.params)
    ae_p = tuple(jnp.asarray(b.params) for b in ae_list)

    def rates(x: jax.Array) -> jax.Array:
        return _rates(de_b, x, u0, played, ae_list, de_p, ae_p)[0]

    jac = np.asarray(jax.jacfwd(rates)(x0), dtype=np.float64)
    if not np.all(np.isfinite(jac)):
        raise ValueError("the model's Jacobian at the operating point is not finite")
    eig = np.linalg.eigvals(jac)
    eig = eig[np.lexsort((-eig.imag, -eig.real))]
    duration = float(np.asarray(data.t)[-1] - np.asarray(data.t)[0])
    scale = np.array([max(float(np.ptp(np.asarray(data[n]))), 1e-12) for n in states])
    drift = np.asarray(rates(x0)) * duration / scale
    return {
        "at_s": float(np.asarray(data.t)[at]),
        "eigenvalues": [[float(v.real), float(v.imag)] for v in eig],
        "max_real": float(np.max(eig.real)),
        "oscillatory": [
            {
                "frequency_hz": float(v.imag / (2 * np.pi)),
                "damping_ratio": float(-v.real / abs(v)),
            }
            for v in eig
            if v.imag > 0
        ],
        "rates": {n: float(r) for n, r in zip(states, drift, strict=True)},
    }


def at_equilibrium(
    de: Block | _EquationsLike,
    data: Dataset,
    free: Sequence[str],
    *,
    hold: Sequence[str] = (),
    ae: Block | _EquationsLike | Sequence[Block | _EquationsLike] | None = None,
    mode: Mode = "dae",
    iterations: int = 50,
) -> tuple[Dataset, dict[str, Any]]:
    """``data`` with the model put at equilibrium at its first sample, as a simulator
    initialises a dynamic model from a power flow: the channels named in ``free`` are solved so
    that the state derivatives vanish there and the algebraic variables named in ``hold`` take
    their recorded first values (the power flow's P and Q at the terminal): least squares,
    Gauss-Newton on the model at the first sample, each state's derivative scaled by the
    state's range in ``data``, each held variable's mismatch by its own. Every other state and
    played-in signal keeps its first sample. With the terminal voltage and angle played in,
    the states and the constant inputs free and P and Q held, this is the textbook
    initialisation of a machine from a power flow (as many equations as unknowns).

    A free *input* (a field voltage, a mechanical power: what an exciter or a governor would
    hold) becomes constant at its solved value over the whole recording; a free *state* (one
    the recording does not measure, or measures in other coordinates) gets its solved value as
    its first sample. Two simulators of one machine then start from the same operating point
    even where their equations differ slightly (a discovered model's input gain 0.5 % off the
    family's ties shifts its own equilibrium, and played in as the other simulator set it, the
    input would drive a drift that is no part of the dynamics compared).

    Returns the recording and a report: per free channel its solved value (``solved``), and
    the scaled residual norm before and after (``residual``). Raises ``ValueError`` if a free
    channel is neither a state of the model nor a signal it plays in, or if the solve turns
    non-finite."""
    de_b = as_block(de)
    ae_list = _ae_blocks(ae)
    played, _ = _prepare(de_b, ae_list, data, mode)
    states = de_b.targets
    unknown = [n for n in free if n not in states and n not in played]
    if unknown:
        raise ValueError(
            f"{unknown} are neither states of the model nor signals it plays in "
            f"(states {list(states)}, played in {list(played)})"
        )
    computed = [n for b in ae_list for n in b.targets]
    not_computed = [n for n in hold if n not in computed or n not in data]
    if not_computed:
        raise ValueError(
            f"{not_computed} are not algebraic variables both the model computes "
            f"({computed}) and the data hold"
        )
    target = np.array([float(np.asarray(data[n])[0]) for n in hold])
    spread = np.array([max(float(np.ptp(np.asarray(data[n]))), 1e-6) for n in hold])
    x0 = np.array([float(np.asarray(data[n])[0]) for n in states])
    u0 = np.array([float(np.asarray(data[n])[0]) for n in played])
    scale = np.array([max(float(np.ptp(np.asarray(data[n]))), 1e-6) for n in states])
    in_x = [(k, states.index(n)) for k, n in enumerate(free) if n in states]
    in_u = [(k, played.index(n)) for k, n in enumerate(free) if n not in states]
    de_p = jnp.asarray(de_b.params)
    ae_p = tuple(jnp.asarray(b.params) for b in ae_list)

    def residual(z: jax.Array) -> jax.Array:
        x, u = jnp.asarray(x0), jnp.asarray(u0)
        for k, i in in_x:
            x = x.at[i].set(z[k])
        for k, j in in_u:
            u = u.at[j].set(z[k])
        dx, env = _rates(de_b, x, u, played, ae_list, de_p, ae_p)
        rates = dx / scale
        if not hold:
            return rates
        held = jnp.stack([jnp.asarray(env[n], dtype=x.dtype) for n in hold])
        return jnp.concatenate([rates, (held - target) / spread])

    f = jax.jit(residual)
    jac = jax.jit(jax.jacfwd(residual))
    z = np.array([float(np.asarray(data[n])[0]) for n in free])
    before = float(np.linalg.norm(f(jnp.asarray(z))))
    for _ in range(iterations):
        r = np.asarray(f(jnp.asarray(z)))
        step = np.linalg.lstsq(np.asarray(jac(jnp.asarray(z))), -r, rcond=None)[0]
        z = z + step
        if not np.all(np.isfinite(z)):
            raise ValueError("the equilibrium solve turned non-finite")
        if np.max(np.abs(step)) <= 1e-12 * (1.0 + np.max(np.abs(z))):
            break
    after = float(np.linalg.norm(f(jnp.asarray(z))))
    values: dict[str, np.ndarray] = {}
    for k, name in enumerate(free):
        series = np.asarray(data[name], dtype=np.float64).copy()
        if name in states:
            series[0] = z[k]
        else:
            series[:] = z[k]
        values[name] = series
    report = {
        "solved": {n: float(v) for n, v in zip(free, z, strict=True)},
        "residual": {"before": before, "after": after},
    }
    return data.with_values(values), report


# ------------------------------------------------------------------------------------------------
# metrics
# ------------------------------------------------------------------------------------------------


def fault_window(data: Dataset, after: float = 1.0) -> tuple[float, float] | None:
    """The fault window ``(first event, last event + after)``; None if there are no events."""
    if not data.events:
        return None
    return (float(data.events[0]), float(data.events[-1]) + after)


def _series(sim: RolloutResult | Dataset | Mapping[str, Any], name: str) -> np.ndarray:
    if isinstance(sim, (RolloutResult, Dataset)):
        return np.asarray(sim[name], dtype=np.float64)
    return np.asarray(sim[name], dtype=np.float64)


def _state_metrics(
    x_sim: np.ndarray, x: np.ndarray, scale: float, plain_ok: bool
) -> dict[str, float]:
    err = x_sim - x
    if not np.all(np.isfinite(err)):
        inf = float("inf")
        return {
            "mape": inf,
            "mape_plain": inf if plain_ok else float("nan"),
            "r2": -inf,
            "nrmse": inf,
            "nmae": inf,
        }
    ae = np.abs(err)
    ss_tot = float(np.sum((x - x.mean()) ** 2))
    ss_res = float(np.sum(err**2))
    r2 = 1.0 - ss_res / ss_tot if ss_tot > 0 else (1.0 if ss_res == 0 else -float("inf"))
    return {
        "mape": 100.0 * float(np.mean(ae / np.maximum(np.abs(x), scale))),
        "mape_plain": 100.0 * float(np.mean(ae / np.abs(x))) if plain_ok else float("nan"),
        "r2": r2,
        "nrmse": float(np.sqrt(np.mean(err**2))) / scale,
        "nmae": float(np.mean(ae)) / scale,
    }


def _mean(values: Sequence[float]) -> float:
    finite = [v for v in values if not np.isnan(v)]
    return float(np.mean(finite)) if finite else float("nan")


def metrics(
    sim: RolloutResult | Dataset | Mapping[str, Any],
    meas: Dataset,
    states: Sequence[str] | None = None,
    window: tuple[float, float] | Literal["fault"] | None = None,
    *,
    bounded: float = 0.1,
) -> dict[str, Any]:
    """Per-state and mean error metrics of a simulation against a recording (``docs/metrics.md``).

    With ``x`` the measured and ``x^`` the simulated samples of a state and ``s`` its scale,
    the range ``max(x) - min(x)`` over the *whole* measured record (so that window and full
    numbers share a scale; a constant signal uses ``max|x|``, or 1):

    - ``mape``   = 100 mean |x^ - x| / max(|x|, s)     (percent; the floor s tames x near 0)
    - ``mape_plain`` = 100 mean |x^ - x| / |x|, only if min|x| >= ``bounded`` * max|x| over the
      whole record (else NaN, and left out of the mean)
    - ``r2``     = 1 - sum (x^ - x)^2 / sum (x - mean x)^2   (over the samples scored)
    - ``nrmse``  = sqrt(mean (x^ - x)^2) / s
    - ``nmae``   = mean |x^ - x| / s

    Non-finite simulated samples (a diverged rollout) give ``inf`` errors and ``r2 = -inf``.

    Args:
        sim: the simulation (a `RolloutResult`, a Dataset or a mapping name -> [n] on meas.t).
        meas: the recording.
        states: the channels to score (default: the simulated states of a `RolloutResult`, else
            the recording's states).
        window: ``(t0, t1)`` to score only samples with ``t0 <= t <= t1``, ``"fault"`` for
            `fault_window`, or None for the whole record.
        bounded: the threshold of ``mape_plain``.

    Returns:
        ``{"per_state": {name: {metric: value}}, "mean": {metric: value}, "window": (t0, t1) or
        None, "n_samples": int}`` with the metrics of `METRICS`.
    """
    if states is None:
        states = tuple(sim.states) if isinstance(sim, RolloutResult) else meas.state_names
    t = np.asarray(meas.t)
    if window == "fault":
        window = fault_window(meas)
    mask = np.ones_like(t, dtype=bool)
    if window is not None:
        mask = (t >= window[0] - 1e-12) & (t <= window[1] + 1e-12)
    per: dict[str, dict[str, float]] = {}
    for name in states:
        x_full = np.asarray(meas[name], dtype=np.float64)
        x_sim = _series(sim, name)
        if x_sim.shape != x_full.shape:
            raise ValueError(f"simulated {name!r} has shape {x_sim.shape}, measured {x_full.shape}")
        scale = float(np.ptp(x_full))
        if scale <= 0:
            scale = float(np.max(np.abs(x_full))) or 1.0
        amin, amax = float(np.min(np.abs(x_full))), float(np.max(np.abs(x_full)))
        plain_ok = amax > 0 and amin >= bounded * amax
        per[name] = _state_metrics(x_sim[mask], x_full[mask], scale, plain_ok)
    mean = {k: _mean([per[n][k] for n in states]) for k in METRICS}
    return {
        "per_state": per,
        "mean": mean,
        "window": None if window is None else (float(window[0]), float(window[1])),
        "n_samples": int(mask.sum()),
    }


def score(
    sim: RolloutResult | Dataset | Mapping[str, Any],
    meas: Dataset,
    states: Sequence[str] | None = None,
    after: float = 1.0,
) -> dict[str, Any]:
    """`metrics` over the whole record (``"full"``) and the fault window (``"fault"``).

    For a `RolloutResult` also ``diverged`` and ``diverged_at``. Always ``far_off_states``: the
    states whose R^2 over the whole record is below `FAR_OFF_R2`, and ``far_off``: the rollout
    diverged or a state is far off (bounded, but far from the measurement)."""
    out: dict[str, Any] = {"full": metrics(sim, meas, states)}
    window = fault_window(meas, after)
    if window is not None:
        out["fault"] = metrics(sim, meas, states, window)
    if isinstance(sim, RolloutResult):
        out["diverged"] = sim.diverged
        out["diverged_at"] = sim.diverged_at
    per_state = out["full"]["per_state"]
    out["far_off_states"] = [st for st, m in per_state.items() if m["r2"] < FAR_OFF_R2]
    out["far_off"] = bool(out["far_off_states"]) or bool(out.get("diverged", False))
    return out


def r2(pred: np.ndarray, target: np.ndarray) -> float:
    """The coefficient of determination of ``pred`` against ``target``."""
    ss = float(np.sum((target - pred) ** 2))
    return 1.0 - ss / float(np.sum((target - target.mean()) ** 2))


def algebraic_r2(ae: _EquationsLike, recordings: Sequence[Dataset]) -> dict[str, float]:
    """R^2 of each algebraic equation on recordings (states and boundary measured, not
    simulated): how well the AE equations hold on data they were not fitted to."""
    from jaxdmd.data import stack_samples

    skeleton = ae.skeleton()
    data = stack_samples(recordings, recordings[0].names)
    pred = np.asarray(
        skeleton({k: jnp.asarray(v) for k, v in data.items()}, jnp.asarray(ae.params))
    )
    return {t: r2(pred[j], data[t]) for j, t in enumerate(ae.contract.targets)}
