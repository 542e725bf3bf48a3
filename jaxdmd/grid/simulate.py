"""Fault simulation of the IEEE 39-bus system with diffrax.

Network: the 39-bus admittance matrix plus constant-impedance loads y_L = (P_d - j Q_d) / V_0^2
(from the operating point) plus, during the fault, a shunt 1 / (r_f + j x_f) at the faulted bus.
The network is Kron-reduced onto the 10 generator buses for both topologies (pre-/post-fault, and
fault: the fault is cleared without tripping a line). Inside
the vector field the generators' stator equations and the reduced network are solved together as
one real 20 x 20 linear system (exact; it also covers salient stators X_d != X_q). Bus voltages
are reconstructed at the output times only.

Discontinuities are handled exactly: the switching times are diffrax ``jump_ts`` (of a
``ClipStepSizeController``), so no step straddles them: a step ends just before the switch and
the next one restarts (FSAL reset) just after it, with the network of the new topology. A
sample that falls exactly on a switching time belongs to the *later* topology (right-continuous
algebraic channels and derivatives; the states are continuous).
"""

from __future__ import annotations

import functools
import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jaxdmd.grid.machines import (
    STATE_LAYOUT,
    MachineModel,
    MachineParams,
    Setpoints,
    as_model,
    electrical_power,
    initial_state,
    machine_params,
    machine_rhs,
    stator_currents,
)
from jaxdmd.grid.network import case39, kron_reduce
from jaxdmd.grid.operating import OperatingPoint

ALGEBRAIC = ("i_d", "i_q", "P_e", "Q_e", "v_d", "v_q", "V", "theta", "P_m", "v_f")

# Loss of synchronism: a machine whose rotor angle relative to the centre of inertia moves more
# than pi from where it started has slipped a pole; a speed relative to the centre of inertia
# beyond MAX_SPEED_DEVIATION pu (3 Hz at 60 Hz) does not happen in a run that stays in step
# (the faults of the benchmark move the speeds by less than 0.01 pu).
MAX_ANGLE_EXCURSION = math.pi
MAX_SPEED_DEVIATION = 0.05


class SynchronismWarning(RuntimeWarning):
    """A simulated machine lost synchronism (its data are not those of a stable system)."""


@dataclass(frozen=True)
class Fault:
    """Three-phase-to-ground fault: shunt ``1 / (r + j x)`` pu at ``bus``, ``t_on <= t < t_off``."""

    bus: int = 15
    t_on: float = 1.0
    t_off: float = 1.1
    r: float = 0.0
    x: float = 1e-4

    def __post_init__(self):
        case39().bus_index(self.bus)  # raises for an unknown bus
        if not 0.0 < self.t_on < self.t_off:
            raise ValueError(f"need 0 < t_on < t_off, got t_on={self.t_on}, t_off={self.t_off}")
        if self.r < 0 or self.x < 0 or self.r + self.x <= 0:
            raise ValueError(
                f"fault impedance must be non-negative and nonzero, got {self.r}+j{self.x}"
            )

    @property
    def events(self) -> tuple[float, float]:
        return (self.t_on, self.t_off)


@dataclass(frozen=True)
class SolverSettings:
    """Integration settings (static under jit)."""

    solver: str = "tsit5"  # "tsit5" or "kvaerno5"
    rtol: float = 1e-9
    atol: float = 1e-11
    pcoeff: float = 0.0
    icoeff: float = 1.0
    max_steps: int = 100_000


DEFAULT_SETTINGS = SolverSettings()


class SimResult(eqx.Module):
    """Simulation output; arrays may carry leading batch axes (vmap over operating points).

    Attributes:
        t: output times, shape (T,).
        x: states in ``STATE_LAYOUT`` order, shape (..., T, 7, 10).
        dx: exact state derivatives (the vector field at the output states), same shape.
        alg: algebraic channels ``ALGEBRAIC`` -> shape (..., T, 10).
        bus_V, bus_theta: all bus voltage magnitudes and angles (rad), shape (..., T, 39).
        model: the machine model (static).
        fault: the fault (static; None for an undisturbed run).
    """

    t: jax.Array
    x: jax.Array
    dx: jax.Array
    alg: dict[str, jax.Array]
    bus_V: jax.Array
    bus_theta: jax.Array
    model: MachineModel = eqx.field(static=True)
    fault: Fault | None = eqx.field(static=True)

    def state(self, name: str) -> jax.Array:
        """State ``name`` (any of ``STATE_LAYOUT``), shape (..., T, 10)."""
        return self.x[..., STATE_LAYOUT.index(name), :]

    def derivative(self, name: str) -> jax.Array:
        """Exact time derivative of state ``name``, shape (..., T, 10)."""
        return self.dx[..., STATE_LAYOUT.index(name), :]


def _real_form(Y: jax.Array) -> jax.Array:
    G, B = Y.real, Y.imag
    return jnp.block([[G, -B], [B, G]])


def network_solve(p: MachineParams, x: jax.Array, Yr: jax.Array) -> jax.Array:
    """Generator terminal voltages (complex, shape (10,)) for states ``x`` (7, 10) and the real
    form ``Yr`` (20 x 20) of the Kron-reduced network (stator and network solved together)."""
    ng = x.shape[-1]
    delta = x[0]
    e_q, e_d = x[2], p.w_edpp * x[4] + p.w_edp * x[3]
    s, c = jnp.sin(delta), jnp.cos(delta)
    k = 1.0 / (p.r_a**2 + p.X_d * p.X_q)
    a11, a12, a21, a22 = k * p.r_a, k * p.X_q, -k * p.X_d, k * p.r_a
    # B = T A with T = [[s, c], [-c, s]] (dq -> network frame); G = B T^T
    b11, b12 = s * a11 + c * a21, s * a12 + c * a22
    b21, b22 = -c * a11 + s * a21, -c * a12 + s * a22
    g11, g12 = b11 * s + b12 * c, -b11 * c + b12 * s
    g21, g22 = b21 * s + b22 * c, -b21 * c + b22 * s
    Gm = jnp.block([[jnp.diag(g11), jnp.diag(g12)], [jnp.diag(g21), jnp.diag(g22)]])
    J = jnp.concatenate([b11 * e_d + b12 * e_q, b21 * e_d + b22 * e_q])
    v = jnp.linalg.solve(Yr + Gm, J)
    return v[:ng] + 1j * v[ng:]


def _dq(x: jax.Array, V: jax.Array) -> tuple[jax.Array, jax.Array]:
    s, c = jnp.sin(x[0]), jnp.cos(x[0])
    return s * V.real - c * V.imag, c * V.real + s * V.imag


def _network_at(t, nets, events):
    """The entry of ``nets`` (pre-fault, faulted) in force at time ``t``.

    Right-continuous: from ``t_on`` (inclusive) to ``t_off`` (exclusive) the faulted network."""
    if events is None:
        return nets[0]
    on = (t >= events[0]) & (t < events[1])
    return jax.tree_util.tree_map(lambda a, b: jnp.where(on, b, a), nets[0], nets[1])


def _vector_field(t, x, args):
    p, sp, Yrs, events = args
    Yr = _network_at(t, Yrs, events)
    V = network_solve(p, x, Yr)
    v_d, v_q = _dq(x, V)
    return machine_rhs(p, sp, x, v_d, v_q, jnp.abs(V))


def _outputs(p: MachineParams, sp: Setpoints, t, x: jax.Array, nets, events):
    Yr, W = _network_at(t, nets, events)
    V = network_solve(p, x, Yr)
    v_d, v_q = _dq(x, V)
    i_d, i_q = stator_currents(p, x, v_d, v_q)
    P_e, Q = electrical_power(p, v_d, v_q, i_d, i_q)
    dx = machine_rhs(p, sp, x, v_d, v_q, jnp.abs(V))
    Vb = W @ V
    alg = dict(
        i_d=i_d, i_q=i_q, P_e=P_e, Q_e=Q, v_d=v_d, v_q=v_q, V=jnp.abs(V), theta=jnp.angle(V),
        P_m=x[6], v_f=x[5],
    )  # fmt: skip
    return dx, alg, jnp.abs(Vb), jnp.angle(Vb)


def _solver(name: str):
    name = name.lower()
    if name == "tsit5":
        return dfx.Tsit5()
    if name == "kvaerno5":
        return dfx.Kvaerno5()
    raise ValueError(f"unknown solver {name!r}; choose 'tsit5' or 'kvaerno5'")


def _simulate_impl(op, p, fault, t_end, dt, settings):
    case = case39()
    gb = case.gen_bus
    Vbus = op.Vm * jnp.exp(1j * op.Va)
    Y = jnp.asarray(case.Y) + jnp.diag((op.Pd - 1j * op.Qd) / op.Vm**2)
    x0, sp = initial_state(p, Vbus[gb], op.Pg + 1j * op.Qg)
    Yred, W = kron_reduce(Y, gb)
    nets = [(_real_form(Yred), W)]
    events = None
    if fault is not None:
        if not fault.t_off < t_end:
            raise ValueError(f"the fault must clear before t_end={t_end}, got t_off={fault.t_off}")
        k = case.bus_index(fault.bus)
        Yf = Y.at[k, k].add(1.0 / (fault.r + 1j * fault.x))
        Yred_f, W_f = kron_reduce(Yf, gb)
        nets.append((_real_form(Yred_f), W_f))
        events = (fault.t_on, fault.t_off)
    n = round(t_end / dt) + 1
    ts = jnp.linspace(0.0, t_end, n)
    inner = dfx.PIDController(
        rtol=settings.rtol, atol=settings.atol, pcoeff=settings.pcoeff, icoeff=settings.icoeff
    )
    # the solver steps exactly up to each switching time and restarts just after it
    ctrl = dfx.ClipStepSizeController(inner, jump_ts=events) if events else inner
    args = (p, sp, [Yr for Yr, _ in nets], events)
    sol = dfx.diffeqsolve(
        dfx.ODETerm(_vector_field), _solver(settings.solver), 0.0, t_end, 1e-3, x0, args,
        saveat=dfx.SaveAt(ts=ts), stepsize_controller=ctrl, max_steps=settings.max_steps,
    )  # fmt: skip
    dx, alg, bV, bT = jax.vmap(lambda t, x: _outputs(p, sp, t, x, nets, events))(ts, sol.ys)
    return dict(t=ts, x=sol.ys, dx=dx, alg=alg, bus_V=bV, bus_theta=bT)


@functools.partial(jax.jit, static_argnames=("fault", "t_end", "dt", "settings", "batched"))
def _run(op, p, *, fault, t_end, dt, settings, batched):
    f = lambda o: _simulate_impl(o, p, fault, t_end, dt, settings)  # noqa: E731
    if batched:
        out = jax.vmap(f)(op)
        out["t"] = out["t"][0]
        return out
    return f(op)


def simulate(
    op: OperatingPoint,
    model: MachineModel | str = "psat-5.1",
    fault: Fault | int | None = 15,
    *,
    t_end: float = 10.0,
    dt: float = 0.01,
    settings: SolverSettings = DEFAULT_SETTINGS,
    params: MachineParams | None = None,
    warn: bool = True,
) -> SimResult:
    """Simulate the 39-bus system from operating point(s) ``op`` through a fault.

    Args:
        op: an :class:`OperatingPoint`; with a leading batch axis the runs are vmapped.
        model: machine model (name or :class:`MachineModel`), applied to all 10 generators.
        fault: a :class:`Fault`, a bus number (fault on at 1.0 s, cleared at 1.1 s, x_f = 1e-4),
            or None for an undisturbed run.
        t_end: simulated time in s; outputs at ``0, dt, ..., t_end``.
        dt: output sampling period in s.
        settings: solver and tolerances.
        params: override the parameter arrays built from ``model`` (advanced).
        warn: warn (:class:`SynchronismWarning`) when a machine loses synchronism (see
            :func:`out_of_step`).

    Returns:
        a :class:`SimResult`. One compilation serves every model and option (they are data);
        a new fault bus/time, ``t_end``, ``dt`` or batch shape compiles again.
    """
    model = as_model(model)
    if isinstance(fault, int | np.integer):
        fault = Fault(bus=int(fault))
    elif fault is not None and not isinstance(fault, Fault):
        raise TypeError(f"fault must be a Fault, a bus number or None, got {fault!r}")
    if dt <= 0 or t_end <= 0:
        raise ValueError("t_end and dt must be positive")
    p = params if params is not None else machine_params(model)
    batched = op.Vm.ndim == 2
    if op.Vm.ndim not in (1, 2):
        raise ValueError("op must be one operating point or a stack along one leading axis")
    out = _run(
        op, p, fault=fault, t_end=float(t_end), dt=float(dt), settings=settings, batched=batched
    )
    result = SimResult(model=model, fault=fault, **out)
    if warn:
        runs = out_of_step(result, inertia=p.M)
        where = f"the fault at bus {fault.bus}" if fault is not None else "an undisturbed run"
        warn_out_of_step(runs, [f"run {i}" for i in range(len(runs))] if batched else [where])
    return result


def out_of_step(result: SimResult, inertia: jax.Array | None = None) -> list[tuple[int, ...]]:
    """The generators (bus numbers) that lose synchronism, one tuple per run (one for an
    unbatched result).

    A generator is out of step when its rotor angle relative to the centre of inertia (the
    inertia-weighted mean angle) moves more than ``MAX_ANGLE_EXCURSION`` (pi) from its initial
    value, or its speed relative to the centre of inertia exceeds ``MAX_SPEED_DEVIATION`` pu.
    ``inertia``: the machines' M (default: those of ``result.model``).
    """
    M = np.asarray(machine_params(result.model).M if inertia is None else inertia, np.float64)
    delta = np.asarray(result.state("delta"), np.float64)
    omega = np.asarray(result.state("omega"), np.float64)
    batched = delta.ndim == 3
    if not batched:
        delta, omega = delta[None], omega[None]
    weights = M / M.sum()
    rel = delta - (delta * weights).sum(-1, keepdims=True)  # [runs, T, 10]
    excursion = np.abs(rel - rel[:, :1]).max(axis=1)
    speed = np.abs(omega - (omega * weights).sum(-1, keepdims=True)).max(axis=1)
    bad = ~(excursion <= MAX_ANGLE_EXCURSION) | ~(speed <= MAX_SPEED_DEVIATION)  # NaN: bad too
    buses = case39().gen_bus_numbers
    return [tuple(int(buses[g]) for g in np.flatnonzero(row)) for row in bad]


def warn_out_of_step(runs: Sequence[tuple[int, ...]], names: Sequence[str]) -> None:
    """Warn (:class:`SynchronismWarning`) naming the runs and generators out of step, if any."""
    lost = [
        f"{name}: generators {list(gens)}" for name, gens in zip(names, runs, strict=True) if gens
    ]
    if lost:
        warnings.warn(
            "loss of synchronism (a rotor angle moves more than pi from its start relative to "
            f"the centre of inertia, or a speed deviates more than {MAX_SPEED_DEVIATION} pu): "
            + "; ".join(lost)
            + ". The data are not those of a stable system.",
            SynchronismWarning,
            stacklevel=3,
        )
