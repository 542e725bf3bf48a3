"""Synchronous machine models of the IEEE 39-bus benchmark, with optional controls.

All models share one state layout per generator, ``STATE_LAYOUT`` =
``(delta, omega, e_qp, e_dp, e_dpp, v_f, P_m)``; a model freezes the states it does not have
(their derivative is multiplied by a 0/1 mask). Model choice and options are therefore *data*
(:class:`MachineParams`, a pytree of arrays), so one compiled simulator serves every model.

Stator (all models, dq frame, v_d = V sin(delta - theta), v_q = V cos(delta - theta)):

    0 = v_q + r_a i_q - e_q + X_d i_d          0 = v_d + r_a i_d - e_d - X_q i_q

==============  ======================  ==========  ==========  ======================
model           states                  e_q         e_d         X_d, X_q
==============  ======================  ==========  ==========  ======================
``psat-5.1``    delta omega e'_q e'_d   e'_q        e''_d       x'_d, x'_d (PSAT 5.1)
                e''_d
``two-axis``    delta omega e'_q e'_d   e'_q        e'_d        x'_d, x'_q
``one-axis``    delta omega e'_q        e'_q        0           x'_d, x_q
``classical``   delta omega             E' const.   0           x'_d, x'_d
==============  ======================  ==========  ==========  ======================

Differential equations (PSAT 5.1; the simpler models drop terms as their name says):

    d delta/dt = Omega_b (omega - 1)
    M d omega/dt = P_m - P_e - D (omega - 1)
    T'_d0 d e'_q/dt = -f_s(e'_q) - (x_d - x'_d) i_d + v_f
    T'_q0 d e'_d/dt = -e'_d + (x_q - x'_q - gamma_q) i_q          (gamma_q = 0 for two-axis)
    T''_q0 d e''_d/dt = -e''_d + e'_d + (x'_q - x'_d + gamma_q) i_q
    gamma_q = (x'_d / x'_q) (T''_q0 / T'_q0) (x_q - x'_q)

Saturation f_s: identity for e <= 0.8, else the quadratic through (0.8, 0.8), (1.0, 1 - S_1.0),
(1.2, 1.2 (1 - S_1.2)) (PSAT ``synsat.m`` as restated in reference/psat-syn-5.1.md).

Exciter (optional, first-order AVR, no limits):  T_A dv_f/dt = K_A (V_ref - V) - v_f,
with V_ref = V_0 + v_f0 / K_A so that the operating point is an equilibrium.

Governor-turbine (optional, first order with droop):  T_g dP_m/dt = P_ref - P_m - (omega - 1)/R,
P_ref = P_m0; R in pu of the system base is ``droop * BASE_MVA / P_max`` (``droop`` on the
machine's own rating, P_max from case39).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jaxdmd.grid.network import case39

STATE_LAYOUT: tuple[str, ...] = ("delta", "omega", "e_qp", "e_dp", "e_dpp", "v_f", "P_m")

# Pai (1989) New England data on the 100 MVA system base (reference/psat-syn-5.1.md).
# columns: bus, H, x_d, x'_d, x_q, x'_q, T'_d0, T'_q0, r_a, x_l
MACHINE_TABLE: tuple[tuple[float, ...], ...] = (
    (30, 42.0, 0.1, 0.031, 0.069, 0.008, 10.2, 0.0, 0.00014, 0.0125),
    (31, 30.3, 0.295, 0.0697, 0.282, 0.170, 6.56, 1.5, 0.0027, 0.035),
    (32, 35.8, 0.2495, 0.0531, 0.237, 0.0876, 5.7, 1.5, 0.000386, 0.0304),
    (33, 28.6, 0.262, 0.0436, 0.258, 0.166, 5.69, 1.5, 0.000222, 0.0295),
    (34, 26.0, 0.67, 0.132, 0.62, 0.166, 5.4, 0.44, 0.00014, 0.054),
    (35, 34.8, 0.254, 0.05, 0.241, 0.0814, 7.3, 0.4, 0.00615, 0.0224),
    (36, 26.4, 0.295, 0.049, 0.292, 0.186, 5.66, 1.5, 0.000268, 0.0322),
    (37, 24.3, 0.29, 0.057, 0.280, 0.0911, 6.7, 0.41, 0.000686, 0.028),
    (38, 34.5, 0.2106, 0.057, 0.205, 0.0587, 4.79, 1.96, 0.0003, 0.0298),
    (39, 500.0, 0.02, 0.006, 0.019, 0.008, 7.0, 0.7, 0.0001, 0.003),
)
T_QPP0_DEFAULT = 0.04  # s, no public source; a common choice (documented)
T_QP0_FALLBACK = 0.8  # s, PSAT's replacement for a non-positive T'_q0 (bus 30)

MODEL_STATES: dict[str, tuple[str, ...]] = {
    "psat-5.1": ("delta", "omega", "e_qp", "e_dp", "e_dpp"),
    "two-axis": ("delta", "omega", "e_qp", "e_dp"),
    "one-axis": ("delta", "omega", "e_qp"),
    "classical": ("delta", "omega"),
}
_ALIASES = {
    "5.1": "psat-5.1", "psat5.1": "psat-5.1", "psat": "psat-5.1", "5": "psat-5.1",
    "order-5": "psat-5.1", "4": "two-axis", "order-4": "two-axis", "3": "one-axis",
    "order-3": "one-axis", "2": "classical", "order-2": "classical",
}  # fmt: skip


def canonical_model_name(name: str) -> str:
    """Canonical model name for ``name`` (aliases such as ``"5.1"``, ``"order-4"`` accepted)."""
    key = str(name).strip().lower()
    key = _ALIASES.get(key, key)
    if key not in MODEL_STATES:
        raise ValueError(
            f"unknown machine model {name!r}; choose one of {sorted(MODEL_STATES)} "
            f"(aliases {sorted(_ALIASES)})"
        )
    return key


@dataclass(frozen=True)
class Exciter:
    """First-order AVR ``T_A dv_f/dt = K_A (V_ref - V) - v_f`` (no limits)."""

    K_A: float = 20.0
    T_A: float = 0.2


@dataclass(frozen=True)
class Governor:
    """Turbine-governor ``T_g dP_m/dt = P_ref - P_m - (omega - 1)/R``.

    ``droop`` is on the machine's rating (P_max); R on the system base is derived from it."""

    droop: float = 0.05
    T_g: float = 0.5


@dataclass(frozen=True)
class MachineModel:
    """Machine model and options (hashable configuration).

    Attributes:
        name: ``"psat-5.1"`` (default, the paper's), ``"two-axis"``, ``"one-axis"`` or
            ``"classical"``.
        damping: D in pu power per pu speed on 100 MVA (scalar or one per generator); 0 default.
        saturation: ``(S_1.0, S_1.2)`` applied to e'_q, or None (identity, the default).
        exciter: an :class:`Exciter` (v_f becomes a state) or None (constant v_f, default).
        governor: a :class:`Governor` (P_m becomes a state) or None (constant P_m, default).
        T_qpp0: T''_q0 in s (0.04 default, one value or one per generator).
    """

    name: str = "psat-5.1"
    damping: float | tuple[float, ...] = 0.0
    saturation: tuple[float, float] | None = None
    exciter: Exciter | None = None
    governor: Governor | None = None
    T_qpp0: float | tuple[float, ...] = T_QPP0_DEFAULT

    def __post_init__(self):
        object.__setattr__(self, "name", canonical_model_name(self.name))
        for field in ("damping", "T_qpp0"):
            v = getattr(self, field)
            if isinstance(v, Sequence | np.ndarray):
                object.__setattr__(self, field, tuple(float(a) for a in v))
        if self.name == "classical" and (self.exciter or self.saturation):
            raise ValueError("the classical model has constant E': no exciter or saturation")
        if self.saturation is not None:
            s1, s2 = self.saturation
            if not (0.0 <= s1 < 1.0 and 0.0 <= s2 < 1.0):
                raise ValueError(f"saturation factors must lie in [0, 1), got {self.saturation}")

    @property
    def states(self) -> tuple[str, ...]:
        """Names of the model's own states (the dataset's state channels)."""
        return MODEL_STATES[self.name]


def as_model(model: MachineModel | str) -> MachineModel:
    """Accept a model name or a :class:`MachineModel`."""
    return model if isinstance(model, MachineModel) else MachineModel(name=model)


class MachineParams(eqx.Module):
    """Per-generator arrays (shape (10,)) of a machine model; a pytree, so models are data."""

    M: jax.Array
    D: jax.Array
    r_a: jax.Array
    x_d: jax.Array
    x_dp: jax.Array
    X_d: jax.Array  # stator reactance multiplying i_d in the q-axis equation
    X_q: jax.Array  # stator reactance multiplying i_q in the d-axis equation
    X_init: jax.Array  # reactance locating the q axis at initialisation
    T_dp0: jax.Array
    T_qp0: jax.Array
    T_qpp0: jax.Array
    c_edp: jax.Array  # coefficient of i_q in the e'_d equation
    c_edpp: jax.Array  # coefficient of i_q in the e''_d equation
    w_edpp: jax.Array  # weight of e''_d in the d-axis EMF
    w_edp: jax.Array  # weight of e'_d in the d-axis EMF
    sat: jax.Array  # (3, 10): c0, c1, c2 of the quadratic
    K_A: jax.Array
    T_A: jax.Array
    R: jax.Array
    T_g: jax.Array
    mask: jax.Array  # (7, 10): 1 where the state of STATE_LAYOUT is dynamic


def saturation_coefficients(s10: float, s12: float) -> np.ndarray:
    """(c0, c1, c2) of the quadratic through (0.8, 0.8), (1, 1 - S_1.0), (1.2, 1.2 (1 - S_1.2))."""
    e = np.array([0.8, 1.0, 1.2])
    f = np.array([0.8, 1.0 - s10, 1.2 * (1.0 - s12)])
    return np.linalg.solve(np.vander(e, 3, increasing=True), f)


def f_sat(e: jax.Array, sat: jax.Array) -> jax.Array:
    """Saturation function f_s(e'_q): identity up to 0.8, then the quadratic."""
    return jnp.where(e <= 0.8, e, sat[0] + sat[1] * e + sat[2] * e * e)


def machine_params(model: MachineModel | str = "psat-5.1") -> MachineParams:
    """Build the per-generator parameter arrays of ``model`` for the IEEE 39-bus machines."""
    model = as_model(model)
    case = case39()
    tab = np.array(MACHINE_TABLE)
    if tuple(tab[:, 0].astype(int)) != case.gen_bus_numbers:
        raise RuntimeError("machine table does not match the case's generator buses")
    ng = len(tab)
    H, xd, xdp, xq, xqp, Td0, Tq0, ra = (tab[:, k] for k in range(1, 9))
    Tq0 = np.where(Tq0 > 0, Tq0, T_QP0_FALLBACK)
    Tqpp0 = np.broadcast_to(np.asarray(model.T_qpp0, float), (ng,)).copy()
    D = np.broadcast_to(np.asarray(model.damping, float), (ng,)).copy()
    gamma = xdp / xqp * Tqpp0 / Tq0 * (xq - xqp)
    zero, one = np.zeros(ng), np.ones(ng)
    name = model.name
    if name == "psat-5.1":
        X_d, X_q, X_init = xdp, xdp, xq
        c_edp, c_edpp, w5, w4 = xq - xqp - gamma, xqp - xdp + gamma, one, zero
        dyn = (1, 1, 1)
    elif name == "two-axis":
        X_d, X_q, X_init = xdp, xqp, xq
        c_edp, c_edpp, w5, w4 = xq - xqp, zero, zero, one
        dyn = (1, 1, 0)
    elif name == "one-axis":
        X_d, X_q, X_init = xdp, xq, xq
        c_edp, c_edpp, w5, w4 = zero, zero, zero, zero
        dyn = (1, 0, 0)
    else:  # classical
        X_d, X_q, X_init = xdp, xdp, xdp
        c_edp, c_edpp, w5, w4 = zero, zero, zero, zero
        dyn = (0, 0, 0)
    sat = saturation_coefficients(*(model.saturation or (0.0, 0.0)))
    exc, gov = model.exciter, model.governor
    mask = np.array([1, 1, *dyn, exc is not None, gov is not None], float)[:, None] * one
    R = (gov.droop if gov else 0.05) / case.Pmax
    a = jnp.asarray
    return MachineParams(
        M=a(2 * H), D=a(D), r_a=a(ra), x_d=a(xd), x_dp=a(xdp), X_d=a(X_d), X_q=a(X_q),
        X_init=a(X_init), T_dp0=a(Td0), T_qp0=a(Tq0), T_qpp0=a(Tqpp0), c_edp=a(c_edp),
        c_edpp=a(c_edpp), w_edpp=a(w5), w_edp=a(w4), sat=a(np.tile(sat[:, None], (1, ng))),
        K_A=a(one * (exc.K_A if exc else 1.0)), T_A=a(one * (exc.T_A if exc else 1.0)),
        R=a(R), T_g=a(one * (gov.T_g if gov else 1.0)), mask=a(mask),
    )  # fmt: skip


class Setpoints(eqx.Module):
    """Operating-point-dependent constants of the controls (shape (10,) each)."""

    V_ref: jax.Array
    P_ref: jax.Array


def stator_currents(p: MachineParams, x: jax.Array, v_d: jax.Array, v_q: jax.Array):
    """(i_d, i_q) from the stator equations for states ``x`` (7, ng) and terminal v_d, v_q."""
    e_q, e_d = x[2], p.w_edpp * x[4] + p.w_edp * x[3]
    k = 1.0 / (p.r_a**2 + p.X_d * p.X_q)
    i_d = k * (p.r_a * (e_d - v_d) + p.X_q * (e_q - v_q))
    i_q = k * (-p.X_d * (e_d - v_d) + p.r_a * (e_q - v_q))
    return i_d, i_q


def electrical_power(p: MachineParams, v_d, v_q, i_d, i_q):
    """(P_e, Q): air-gap power P_e = P + r_a |i|^2 and the injected reactive power."""
    P_e = (v_d + p.r_a * i_d) * i_d + (v_q + p.r_a * i_q) * i_q
    Q = v_q * i_d - v_d * i_q
    return P_e, Q


def machine_rhs(p: MachineParams, sp: Setpoints, x: jax.Array, v_d, v_q, V) -> jax.Array:
    """Time derivatives of the state layout (7, ng) for given terminal quantities."""
    from jaxdmd.grid.network import OMEGA_B

    _, omega, eqp, edp, edpp, vf, Pm = x
    i_d, i_q = stator_currents(p, x, v_d, v_q)
    P_e, _ = electrical_power(p, v_d, v_q, i_d, i_q)
    dw = omega - 1.0
    d = jnp.stack(
        [
            OMEGA_B * dw,
            (Pm - P_e - p.D * dw) / p.M,
            (-f_sat(eqp, p.sat) - (p.x_d - p.x_dp) * i_d + vf) / p.T_dp0,
            (-edp + p.c_edp * i_q) / p.T_qp0,
            (-edpp + edp + p.c_edpp * i_q) / p.T_qpp0,
            (p.K_A * (sp.V_ref - V) - vf) / p.T_A,
            (sp.P_ref - Pm - dw / p.R) / p.T_g,
        ]
    )
    return d * p.mask


def initial_state(p: MachineParams, V: jax.Array, S: jax.Array) -> tuple[jax.Array, Setpoints]:
    """Equilibrium state (7, ng) and set points from terminal phasors V and injections S."""
    I = jnp.conj(S / V)
    delta = jnp.angle(V + (p.r_a + 1j * p.X_init) * I)
    rot = jnp.exp(-1j * (delta - jnp.pi / 2))
    vdq, idq = V * rot, I * rot
    v_d, v_q, i_d, i_q = vdq.real, vdq.imag, idq.real, idq.imag
    eqp = v_q + p.r_a * i_q + p.X_d * i_d
    e_st = v_d + p.r_a * i_d - p.X_q * i_q
    edp = jnp.where(p.w_edpp > 0, p.c_edp * i_q, e_st)
    vf = f_sat(eqp, p.sat) + (p.x_d - p.x_dp) * i_d
    P_e, _ = electrical_power(p, v_d, v_q, i_d, i_q)
    x0 = jnp.stack([delta, jnp.ones_like(delta), eqp, edp, e_st, vf, P_e])
    return x0, Setpoints(V_ref=jnp.abs(V) + vf / p.K_A, P_ref=P_e)
