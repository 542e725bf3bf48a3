"""Diagnosis from terminal channels alone: what a PMU records (V, theta, P, Q, speed).

A phasor measurement unit at the generator terminal records the voltage magnitude and angle,
the active and reactive power and the frequency; it does not record the rotor angle or the
machine's internal voltages. The field's model validation therefore plays the measured voltage
into the model and compares the simulated P and Q (and speed) with the measured ones. This
module does that and goes on to say which equation is wrong:

1. **Play-in simulation.** The machine model (a built-in family, written with its physical
   parameters: M, x'_d, x_d - x'_d, T'_d0, ... as in ``jaxdmd.grid.machines``) is driven by the
   measured V and theta; the rotor angle and the internal voltages are latent states. Each
   recording starts from the model's own equilibrium at its pre-fault operating point: the
   latent states and the unmeasured inputs (P_m, v_f: held there, which the report says,
   unless step 3 names a governor or exciter) solve
   "every rate vanishes, simulated P and Q equal the measured ones" (Gauss-Newton, inside the
   simulation, so that the fit differentiates through it).
2. **Refit.** The parameters are fitted to the output error (P, Q and omega, each scaled by its
   range) by Levenberg-Marquardt through the simulation (Heun's method on the sample grid, as
   :mod:`jaxdmd.simfit`).
3. **Which equation is wrong.** Every candidate extension (a term with a free coefficient in a
   state equation, or in one of the two stator equations: the algebraic side; or, for an
   unmeasured input, a governor or exciter block around its pre-fault value) is ranked by the
   score (Lagrange-multiplier) test at the refitted model: the drop in the sum of squares that
   freeing its coefficient gives to first order, with the model's own parameters refitted
   alongside (one compiled Jacobian serves every candidate). The best few are refitted in
   full; the one that explains the largest share of the remaining error names the equation and
   the term, if that share exceeds the threshold and the extension also simulates held-out data
   better. Then again from the extended model (forward selection, ``max_terms``).
4. **The gain.** Held-out recordings simulated before and after: NRMSE of P and Q.

Nothing here knows an answer: the candidate terms are a generic pool (a constant, the speed
deviation, each state, current and voltage, the equation's own state squared) offered to every
equation alike.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxdmd.data import Dataset

__all__ = [
    "FAMILIES",
    "TERMINAL_CHANNELS",
    "TerminalConfig",
    "TerminalDiagnosis",
    "candidates",
    "derived",
    "diagnose_terminal",
    "is_terminal",
    "write_terminal_report",
]

TERMINAL_CHANNELS = ("V", "theta", "P", "Q")
"""The channels a terminal diagnosis needs: terminal voltage magnitude and angle [rad], active
and reactive power injected at the terminal (on one power base). Optional: the speed ``omega``
[pu] or the frequency ``f`` [Hz], and the inputs P_m, v_f."""

# state equations and stator equations the candidates may extend
_LABELS = {
    "omega": "d omega/dt (swing)",
    "e_qp": "d e'_q/dt (field winding)",
    "e_dp": "d e'_d/dt (q-axis transient)",
    "e_dpp": "d e''_d/dt (q-axis sub-transient)",
    "stator_q": "stator q-axis equation (0 = v_q + r_a i_q - e_q + X_d i_d)",
    "stator_d": "stator d-axis equation (0 = v_d + r_a i_d - e_d - X_q i_q)",
    "P_m": "mechanical power P_m (not measured)",
    "v_f": "field voltage v_f (not measured)",
}

# An unmeasured input may vary: a first-order block around its pre-fault value, its gain the
# candidate's coefficient (0: constant), its time constant fitted with it.
#   governor  T_g dP_m/dt = P_m0 - P_m - G (omega - omega_0)
#   exciter   T_A dv_f/dt = v_f0 - v_f - K_A (V - V_0)
_BLOCKS = {
    "P_m": ("omega - omega_0", "a governor", "G", "T_g", 0.5),
    "v_f": ("V - V_0", "an exciter", "K_A", "T_A", 0.2),
}
# typical gains, a start for the fit: 5 % droop on the rating (G = rating / 0.05), K_A = 20
_TYPICAL_GAIN = {"P_m": lambda rating: rating / 0.05, "v_f": lambda rating: 20.0}


@dataclass(frozen=True)
class Family:
    """A machine model written with its physical parameters.

    ``states``: the simulated states (delta and omega first; the classical model's constant
    internal voltage is the state e_qp with zero rate). ``params``: parameter names, each with a
    typical value on the machine's own base (``_TYPICAL``) scaled to the data's base.
    """

    name: str
    states: tuple[str, ...]
    params: tuple[str, ...]
    inputs: tuple[str, ...]  # inputs its equations use


FAMILIES: dict[str, Family] = {
    "classical": Family("classical", ("delta", "omega", "e_qp"), ("M", "x_dp", "r_a"), ("P_m",)),
    "one-axis": Family(
        "one-axis",
        ("delta", "omega", "e_qp"),
        ("M", "x_dp", "x_d_minus_x_dp", "T_dp0", "x_q", "r_a"),
        ("P_m", "v_f"),
    ),
    "two-axis": Family(
        "two-axis",
        ("delta", "omega", "e_qp", "e_dp"),
        ("M", "x_dp", "x_d_minus_x_dp", "T_dp0", "x_qp", "x_q_minus_x_qp", "T_qp0", "r_a"),
        ("P_m", "v_f"),
    ),
    "psat-5.1": Family(
        "psat-5.1",
        ("delta", "omega", "e_qp", "e_dp", "e_dpp"),
        ("M", "x_dp", "x_d_minus_x_dp", "T_dp0", "c_edp", "T_qp0", "c_edpp", "T_qpp0", "r_a"),
        ("P_m", "v_f"),
    ),
}

# typical values on the machine's own rating (reactances in pu, times in s, M = 2H in s)
_TYPICAL = {
    "M": 8.0, "x_dp": 0.3, "x_d_minus_x_dp": 1.4, "T_dp0": 6.0, "x_q": 1.7, "x_qp": 0.5,
    "x_q_minus_x_qp": 1.2, "T_qp0": 1.0, "c_edp": 1.0, "c_edpp": 0.5, "T_qpp0": 0.05,
    "r_a": 0.003,
}  # fmt: skip
_IMPEDANCE = {"x_dp", "x_d_minus_x_dp", "x_q", "x_qp", "x_q_minus_x_qp", "c_edp", "c_edpp", "r_a"}


_STATOR_POOL = ("1", "i_d", "i_q")  # affine in the currents: the stator stays a linear solve


def _de_pool(family: Family) -> tuple[str, ...]:
    """The generic terms a state equation may gain (its own state squared among them)."""
    latent = family.states[2:] if family.name != "classical" else ()
    return ("1", "omega - 1", *latent, "i_d", "i_q", "v_d", "v_q", "V",
            *(f"{s}**2" for s in latent))  # fmt: skip


def _dynamic(family: Family) -> tuple[str, ...]:
    """The state equations with parameters (all but d delta/dt = Omega_b (omega - 1))."""
    return tuple(s for s in family.states[1:] if not (family.name == "classical" and s == "e_qp"))


def candidates(family: Family, measured: Sequence[str] = ()) -> tuple[tuple[str, str], ...]:
    """Every (equation, term) pair a diagnosis may add, in a fixed order: the same pool for
    every state equation (a squared state only in its own), the stator pool for both stator
    equations. A constant that an unmeasured input absorbs is no candidate: the equilibrium
    solves for P_m (a constant in d omega/dt) and v_f (a constant in d e'_q/dt, or in the
    q-axis stator equation, which shifts e'_q), so the data cannot see it."""
    absorbed = set()
    if "P_m" not in measured:
        absorbed.add(("omega", "1"))
    if "v_f" not in measured or family.name == "classical":  # classical: E' is solved for
        absorbed |= {("e_qp", "1"), ("stator_q", "1")}
    out = [
        (eq, term)
        for eq in _dynamic(family)
        for term in _de_pool(family)
        if not term.endswith("**2") or term == f"{eq}**2"
    ]
    out += [(eq, term) for eq in ("stator_q", "stator_d") for term in _STATOR_POOL]
    out += [(u, _BLOCKS[u][0]) for u in family.inputs if u not in measured]
    return tuple(c for c in out if c not in absorbed)


# ------------------------------------------------------------------------------------------------
# the model
# ------------------------------------------------------------------------------------------------


class _Machine:
    """The family's equations with extension coefficients ``c`` (one per candidate)."""

    def __init__(self, family: Family, omega_b: float, measured: Sequence[str] = ()) -> None:
        self.family = family
        self.omega_b = omega_b
        self.measured = tuple(u for u in family.inputs if u in measured)
        self.cands = candidates(family, measured)
        self.index = {name: i for i, name in enumerate(family.params)}
        self.equations = _dynamic(family)
        self.pool = _de_pool(family)
        # the unmeasured inputs: each a state of its block (held with a zero gain)
        self.blocks = tuple(u for u in family.inputs if u not in self.measured)
        # the coefficient vector: one per candidate, then each block's inverse time constant
        self.n_c = len(self.cands) + len(self.blocks)
        self.tau = {u: len(self.cands) + j for j, u in enumerate(self.blocks)}
        de = [(k, eq, t) for k, (eq, t) in enumerate(self.cands) if eq in self.equations]
        st = [(k, eq, t) for k, (eq, t) in enumerate(self.cands) if eq.startswith("stator")]
        self.de_k = np.asarray([k for k, _, _ in de], dtype=int)
        self.de_rc = (
            np.asarray([self.equations.index(eq) for _, eq, _ in de], dtype=int),
            np.asarray([self.pool.index(t) for _, _, t in de], dtype=int),
        )
        self.st_k = np.asarray([k for k, _, _ in st], dtype=int)
        self.st_rc = (
            np.asarray([("stator_q", "stator_d").index(eq) for _, eq, _ in st], dtype=int),
            np.asarray([_STATOR_POOL.index(t) for _, _, t in st], dtype=int),
        )

    def _p(self, theta: jax.Array, name: str) -> jax.Array:
        return theta[self.index[name]]

    def c0(self) -> np.ndarray:
        """The coefficients of the model as given: no term added, blocks at typical speed."""
        c = np.zeros(self.n_c)
        for u, k in self.tau.items():
            c[k] = 1.0 / _BLOCKS[u][4]
        return c

    def block(self, k: int | None) -> int | None:
        """The inverse time constant's index that comes with candidate ``k`` (a block)."""
        if k is None or self.cands[k][0] not in self.tau:
            return None
        return self.tau[self.cands[k][0]]

    def block_rates(
        self, c: jax.Array, x: dict[str, jax.Array], V: jax.Array, ref: dict[str, jax.Array]
    ) -> dict[str, jax.Array]:
        """d/dt of the unmeasured inputs (zero with a zero gain: held at the pre-fault value)."""
        out = {}
        for u in self.blocks:
            gain, inv_t = c[self.cands.index((u, _BLOCKS[u][0]))], c[self.tau[u]]
            drive = x["omega"] - ref["omega"] if u == "P_m" else V - ref["V"]
            out[u] = inv_t * (ref[u] - x[u] - gain * drive)
        return out

    def reactances(self, theta: jax.Array) -> tuple[jax.Array, jax.Array]:
        """The stator's X_d (multiplying i_d in the q-axis equation) and X_q (i_q in the d-axis
        one): x'_d on both axes but in the two-axis (x'_q) and one-axis (x_q) models."""
        X_d = self._p(theta, "x_dp")
        X_q = {"two-axis": "x_qp", "one-axis": "x_q"}.get(self.family.name)
        return X_d, X_d if X_q is None else self._p(theta, X_q)

    def electrical(
        self, theta: jax.Array, c: jax.Array, x: dict[str, jax.Array], V: jax.Array, th: jax.Array
    ) -> dict[str, jax.Array]:
        """Currents and powers for states ``x`` and terminal voltage V at angle ``th``."""
        f = self.family.name
        v_d, v_q = V * jnp.sin(x["delta"] - th), V * jnp.cos(x["delta"] - th)
        r_a = self._p(theta, "r_a")
        X_d, X_q = self.reactances(theta)
        e_q = x["e_qp"]
        e_d = {"psat-5.1": "e_dpp", "two-axis": "e_dp"}.get(f)
        e_d = x[e_d] if e_d else jnp.zeros_like(V)
        C = jnp.zeros((2, 3), dtype=c.dtype).at[self.st_rc].set(c[self.st_k])
        # (X_d + C_qd) i_d + (r_a + C_qq) i_q = e_q - v_q - C_q1
        # (r_a + C_dd) i_d + (-X_q + C_dq) i_q = e_d - v_d - C_d1
        a11, a12, b1 = X_d + C[0, 1], r_a + C[0, 2], e_q - v_q - C[0, 0]
        a21, a22, b2 = r_a + C[1, 1], -X_q + C[1, 2], e_d - v_d - C[1, 0]
        det = a11 * a22 - a12 * a21
        i_d = (b1 * a22 - a12 * b2) / det
        i_q = (a11 * b2 - a21 * b1) / det
        P = v_d * i_d + v_q * i_q
        return {
            "v_d": v_d, "v_q": v_q, "i_d": i_d, "i_q": i_q, "P": P,
            "Q": v_q * i_d - v_d * i_q, "P_e": P + r_a * (i_d**2 + i_q**2),
        }  # fmt: skip

    def rates(
        self, theta: jax.Array, c: jax.Array, x: dict[str, jax.Array], V: jax.Array,
        th: jax.Array, u: dict[str, jax.Array],
    ) -> tuple[dict[str, jax.Array], dict[str, jax.Array]]:  # fmt: skip
        """d x/dt of every state (the classical model's e_qp: 0), and the currents and powers
        (`electrical`) they used."""
        f, p = self.family.name, lambda n: self._p(theta, n)
        el = self.electrical(theta, c, x, V, th)
        out = {
            "delta": self.omega_b * (x["omega"] - 1.0),
            "omega": (u["P_m"] - el["P_e"]) / p("M"),
        }
        if f == "classical":
            out["e_qp"] = jnp.zeros_like(V)
        else:
            out["e_qp"] = (u["v_f"] - x["e_qp"] - p("x_d_minus_x_dp") * el["i_d"]) / p("T_dp0")
        if f == "two-axis":
            out["e_dp"] = (-x["e_dp"] + p("x_q_minus_x_qp") * el["i_q"]) / p("T_qp0")
        if f == "psat-5.1":
            out["e_dp"] = (-x["e_dp"] + p("c_edp") * el["i_q"]) / p("T_qp0")
            out["e_dpp"] = (-x["e_dpp"] + x["e_dp"] + p("c_edpp") * el["i_q"]) / p("T_qpp0")
        ns = {**x, **el, "V": V}
        values = []
        for t in self.pool:
            if t == "1":
                values.append(jnp.ones_like(V))
            elif t == "omega - 1":
                values.append(x["omega"] - 1.0)
            elif t.endswith("**2"):
                values.append(ns[t[:-3]] ** 2)
            else:
                values.append(ns[t])
        C = jnp.zeros((len(self.equations), len(self.pool)), dtype=c.dtype)
        ext = C.at[self.de_rc].set(c[self.de_k]) @ jnp.stack(values)
        for i, eq in enumerate(self.equations):
            out[eq] = out[eq] + ext[i]
        return out, el

    def start(
        self, theta: jax.Array, V: jax.Array, th: jax.Array, P: jax.Array, Q: jax.Array
    ) -> dict[str, jax.Array]:
        """The base family's equilibrium in closed form (``jaxdmd.grid.machines.initial_state``
        written with this family's parameters): the Gauss-Newton start."""
        f, p = self.family.name, lambda n: self._p(theta, n)
        r_a = p("r_a")
        X_d, X_q = self.reactances(theta)
        x_q = {  # the reactance that locates the q axis
            "psat-5.1": lambda: p("c_edp") + p("c_edpp") + X_d,
            "two-axis": lambda: p("x_q_minus_x_qp") + p("x_qp"),
            "one-axis": lambda: p("x_q"),
            "classical": lambda: X_d,
        }[f]()
        Vc = V * jnp.exp(1j * th)
        current = jnp.conj((P + 1j * Q) / Vc)
        delta = jnp.angle(Vc + (r_a + 1j * x_q) * current)
        rot = jnp.exp(-1j * (delta - jnp.pi / 2))
        v, i = Vc * rot, current * rot
        v_d, v_q, i_d, i_q = v.real, v.imag, i.real, i.imag
        e_qp = v_q + r_a * i_q + X_d * i_d
        e_st = v_d + r_a * i_d - X_q * i_q
        z = {"delta": delta, "e_qp": e_qp}
        if f == "two-axis":
            z["e_dp"] = e_st
        if f == "psat-5.1":
            z["e_dp"], z["e_dpp"] = p("c_edp") * i_q, e_st
        z["P_m"] = v_d * i_d + v_q * i_q + r_a * (i_d**2 + i_q**2)
        xdd = p("x_d_minus_x_dp") if f != "classical" else 0.0
        z["v_f"] = e_qp + xdd * i_d
        return z


# ------------------------------------------------------------------------------------------------
# recordings and the simulation
# ------------------------------------------------------------------------------------------------


def _pre_event(ds: Dataset) -> int:
    """Samples before the first event (at least one): the pre-fault operating point."""
    t = np.asarray(ds.t)
    first = min(ds.events) if ds.events else t[-1] + 1.0
    return max(1, int(np.searchsorted(t, first - 1e-9)))


def _recording(ds: Dataset, outputs: Sequence[str], inputs: Sequence[str]) -> dict[str, Any]:
    """One recording's arrays for the simulation: the steps ``h``, the terminal voltage as
    recorded (the outputs use each sample's own values) and on each interval (``left``,
    ``right``: :func:`jaxdmd.select._played`, held across an event), the measured inputs
    likewise, the outputs ``y`` [O, n] with their ranges, and the pre-fault operating point
    (``start``)."""
    from jaxdmd.select import _played

    ds = ds.with_values({"theta": np.unwrap(np.asarray(ds["theta"], dtype=float))})
    series = {n: np.asarray(ds[n], dtype=float) for n in ("V", "theta", *outputs, *inputs)}
    played = _played(ds, ["V", "theta", *inputs])
    y = np.stack([series[o] for o in outputs])
    scale = np.ptp(y, axis=1)
    k = _pre_event(ds)
    start = {o: np.mean(series[o][:k]) for o in outputs}  # P and Q among them
    start.update(V=series["V"][0], theta=series["theta"][0])
    start.setdefault("omega", np.asarray(1.0))
    start.update({f"{n}_0": series[n][0] for n in inputs})
    return {
        "h": np.diff(np.asarray(ds.t, dtype=float)),
        "V": series["V"],
        "theta": series["theta"],
        "left": played.left,
        "right": played.right,
        "y": y,
        "scale": np.where(scale > 0, scale, 1.0),
        "start": {n: np.asarray(v, dtype=float) for n, v in start.items()},
    }


class _Simulator:
    """Output rollouts of every recording as a function of the parameters and the extension
    coefficients; recordings of equal length are simulated side by side (``vmap``)."""

    def __init__(
        self, machine: _Machine, recordings: Sequence[dict[str, Any]], outputs: Sequence[str],
        substeps: int = 2, newton: int = 12,
    ) -> None:  # fmt: skip
        self.m = machine
        self.outputs = tuple(outputs)
        self.measured = machine.measured
        self.substeps = substeps
        self.newton = newton
        self.n_base = len(machine.family.params)
        self.y = [r["y"] for r in recordings]  # the measured outputs, [O, n] each
        self.scale = [r["scale"] for r in recordings]
        lengths = sorted({y.shape[1] for y in self.y})
        self.groups = []  # (indices, stacked arrays)
        for n in lengths:
            idx = [i for i, y in enumerate(self.y) if y.shape[1] == n]
            stacked = jax.tree.map(lambda *a: jnp.asarray(np.stack(a)),
                                   *(recordings[i] for i in idx))  # fmt: skip
            self.groups.append((np.asarray(idx), stacked))
        self._simulate = jax.jit(self.simulate)

    def _equilibrium(self, theta: jax.Array, c: jax.Array, s: dict[str, jax.Array]) -> tuple[
        dict[str, jax.Array], dict[str, jax.Array]
    ]:  # fmt: skip
        """Latent states and unmeasured inputs at the pre-fault point: Gauss-Newton from the
        base family's closed form, its iterations outside the derivative and one last step
        inside it (exact first derivatives at convergence: the implicit function theorem)."""
        V, th, omega = s["V"], s["theta"], s["omega"]
        z0 = self.m.start(theta, V, th, s["P"], s["Q"])
        latent = [n for n in self.m.family.states if n != "omega"]
        names = [*latent, *self.m.blocks]
        rows = [n for n in self.m.family.states if n != "delta"]

        def split(z: jax.Array) -> tuple[dict[str, jax.Array], dict[str, jax.Array]]:
            x = {n: z[i] for i, n in enumerate(latent)}
            x["omega"] = omega
            u = {n: z[len(latent) + i] for i, n in enumerate(self.m.blocks)}
            u.update({n: s[f"{n}_0"] for n in self.measured})
            return x, u

        def residual(z: jax.Array, theta: jax.Array, c: jax.Array) -> jax.Array:
            x, u = split(z)
            r, el = self.m.rates(theta, c, x, V, th, u)
            return jnp.stack([*(r[n] for n in rows), el["P"] - s["P"], el["Q"] - s["Q"]])

        def newton(z: jax.Array, theta: jax.Array, c: jax.Array) -> jax.Array:
            J = jax.jacfwd(residual)(z, theta, c)
            JtJ = J.T @ J
            damp = 1e-12 * (jnp.trace(JtJ) + 1e-300) * jnp.eye(z.size)
            return z - jnp.linalg.solve(JtJ + damp, J.T @ residual(z, theta, c))

        fixed = jax.lax.stop_gradient((theta, c))
        z = jnp.stack([jax.lax.stop_gradient(z0[n]) for n in names])
        z = jax.lax.fori_loop(0, self.newton, lambda _, z: newton(z, *fixed), z)
        return split(newton(jax.lax.stop_gradient(z), theta, c))

    def _rollout(self, theta: jax.Array, c: jax.Array, rec: dict[str, Any]) -> jax.Array:
        """The outputs ``[O, n]`` of one recording."""
        x0, u0 = self._equilibrium(theta, c, rec["start"])
        # the unmeasured inputs are states of their blocks, at rest with a zero gain
        states = (*self.m.family.states, *self.m.blocks)
        x0 = {**x0, **{u: u0[u] for u in self.m.blocks}}
        ref = {**{u: u0[u] for u in self.m.blocks}, "omega": x0["omega"], "V": rec["start"]["V"]}
        bound = 1e3

        def field(x: jax.Array, w: dict[str, jax.Array]) -> jax.Array:
            xs = {n: x[i] for i, n in enumerate(states)}
            u = {**{n: xs[n] for n in self.m.blocks}, **{n: w[n] for n in self.measured}}
            r, _ = self.m.rates(theta, c, xs, w["V"], w["theta"], u)
            r.update(self.m.block_rates(c, xs, w["V"], ref))
            return jnp.stack([r[n] for n in states])

        def step(x: jax.Array, k: tuple[jax.Array, ...]) -> tuple[jax.Array, jax.Array]:
            h, lo, hi = k
            dt = h / self.substeps
            for j in range(self.substeps):  # Heun's method, as jaxdmd.simfit
                w0, w1 = j / self.substeps, (j + 1) / self.substeps
                k1 = field(x, {n: (1 - w0) * lo[n] + w0 * hi[n] for n in lo})
                k2 = field(x + dt * k1, {n: (1 - w1) * lo[n] + w1 * hi[n] for n in lo})
                x = x + 0.5 * dt * (k1 + k2)
            x = jnp.where(jnp.isfinite(x), jnp.clip(x, -bound, bound), bound)
            return x, x

        x_init = jnp.stack([x0[n] for n in states])
        _, xs = jax.lax.scan(step, x_init, (rec["h"], rec["left"], rec["right"]))
        xs = jnp.concatenate([x_init[None], xs])  # [n, S]
        xd = {n: xs[:, i] for i, n in enumerate(states)}
        el = self.m.electrical(theta, c, xd, rec["V"], rec["theta"])
        out = {**el, "omega": xd["omega"]}
        return jnp.stack([out[o] for o in self.outputs])

    def _runs(self, theta: jax.Array, c: jax.Array):
        """Per group of equal-length recordings: its indices, arrays and outputs [B, O, n]."""
        for idx, group in self.groups:
            yield idx, group, jax.vmap(lambda r: self._rollout(theta, c, r))(group)

    def simulate(self, theta: jax.Array, c: jax.Array) -> list[jax.Array]:
        """The outputs ``[O, n]`` of every recording, in order."""
        out: list[Any] = [None] * len(self.y)
        for idx, _, sims in self._runs(theta, c):
            for j, i in enumerate(idx):
                out[int(i)] = sims[j]
        return out

    def residual(self, theta: jax.Array, c: jax.Array, weights: jax.Array) -> jax.Array:
        """Scaled output errors of every recording (weight 0 leaves a recording out); the sum
        of squares is the sum over recordings and outputs of the NRMSE squared."""
        parts = []
        for idx, group, sims in self._runs(theta, c):
            n = sims.shape[2]
            r = (sims - group["y"]) / group["scale"][:, :, None] / np.sqrt(n)
            parts.append((weights[idx][:, None, None] * r).ravel())
        return jnp.concatenate(parts)

    def outputs_of(self, full: np.ndarray) -> list[np.ndarray]:
        """The simulated outputs of every recording for a fitted vector (parameters, then
        coefficients)."""
        n_b = self.n_base
        runs = self._simulate(jnp.asarray(full[:n_b]), jnp.asarray(full[n_b:]))
        return [np.asarray(y) for y in runs]

    def nrmse(self, sims: Sequence[np.ndarray]) -> dict[str, float]:
        """Mean NRMSE over the recordings per output (inf where a rollout blew up)."""
        errs = []
        for sim, y, scale in zip(sims, self.y, self.scale, strict=True):
            err = np.sqrt(np.mean((sim - y) ** 2, axis=1)) / scale
            errs.append(np.where(np.all(np.isfinite(sim), axis=1), err, np.inf))
        e = np.asarray(errs)
        return {o: float(np.mean(e[:, j])) for j, o in enumerate(self.outputs)}


# ------------------------------------------------------------------------------------------------
# the diagnosis
# ------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class TerminalConfig:
    """Settings of `diagnose_terminal`.

    ``threshold``: share of the refitted model's training output error (sum of squares) one
    term must remove to call the model structurally wrong (the extension must also simulate the
    held-out recordings better). ``refits``: candidates refitted in full after the score test.
    ``max_terms``: terms (or blocks) the forward selection adds at most.
    ``frequency``: the system frequency in Hz (Omega_b = 2 pi f). ``max_steps``: of each
    Levenberg-Marquardt fit.
    """

    threshold: float = 0.2
    refits: int = 4
    max_terms: int = 2
    frequency: float = 60.0
    max_steps: int = 300
    substeps: int = 2


@dataclass(frozen=True)
class TerminalCandidate:
    equation: str
    term: str
    score: float  # first-order share of the training sum of squares freeing it removes
    explained: float | None = None  # share removed once refitted (the best few)
    coefficient: float | None = None

    @property
    def key(self) -> tuple[str, str]:
        return (self.equation, self.term)

    def to_dict(self) -> dict[str, Any]:
        return {
            "equation": self.equation, "label": _LABELS[self.equation], "term": self.term,
            "score": self.score, "explained": self.explained, "coefficient": self.coefficient,
        }  # fmt: skip


@dataclass(frozen=True)
class TerminalDiagnosis:
    """Everything the terminal report shows; `to_dict` is ``diagnosis.json``."""

    family: str
    cause: dict[str, Any]
    candidates: tuple[TerminalCandidate, ...]
    parameters: dict[str, dict[str, float]]  # "refit" / "extended" -> name -> value
    standard_errors: dict[str, dict[str, float]]
    errors: dict[str, dict[str, dict[str, float]]]  # "train"/"held_out" -> model -> output -> NRMSE
    assumptions: tuple[str, ...]
    outputs: tuple[str, ...]
    held_out: str
    wall_time_s: float
    rollouts: dict[str, list[np.ndarray]] = field(repr=False, default_factory=dict)
    measured: list[np.ndarray] = field(repr=False, default_factory=list)
    times: list[np.ndarray] = field(repr=False, default_factory=list)

    def gain(self, output: str) -> float:
        """Held-out NRMSE of ``output`` before / after the extension (1 without one)."""
        held = self.errors["held_out"]
        if "extended" not in held:
            return 1.0
        return held["refit"][output] / max(held["extended"][output], 1e-300)

    def to_dict(self) -> dict[str, Any]:
        return {
            "mode": "terminal",
            "family": self.family,
            "cause": self.cause,
            "candidates": [c.to_dict() for c in self.candidates],
            "parameters": self.parameters,
            "derived": {k: derived(self.family, p) for k, p in self.parameters.items()},
            "standard_errors": self.standard_errors,
            "errors": self.errors,
            "gain": {o: self.gain(o) for o in self.outputs},
            "assumptions": list(self.assumptions),
            "outputs": list(self.outputs),
            "held_out": self.held_out,
            "wall_time_s": self.wall_time_s,
        }


def is_terminal(ds: Dataset, states: Sequence[str]) -> bool:
    """Whether a recording calls for the terminal diagnosis: it has the terminal channels and
    lacks a state the model integrates other than the speed (the rotor angle, usually)."""
    return all(n in ds for n in TERMINAL_CHANNELS) and any(
        s not in ds for s in states if s != "omega"
    )


def _check(datasets: Sequence[Dataset]) -> None:
    for ds in datasets:
        missing = [n for n in TERMINAL_CHANNELS if n not in ds]
        if missing:
            raise ValueError(
                f"{ds.label or 'a recording'}: a terminal diagnosis needs the channels "
                f"{', '.join(TERMINAL_CHANNELS)}; missing {', '.join(missing)} "
                f"(the data have {', '.join(ds.names)})"
            )
        if not ds.events:
            raise ValueError(
                f"{ds.label or 'a recording'}: no events (fault on, clearing) are marked; the "
                "pre-fault operating point is taken before the first event (give --events)"
            )


def _with_speed(ds: Dataset, frequency: float) -> Dataset:
    """The speed omega in pu from a frequency channel ``f`` in Hz where omega is not given."""
    if "omega" in ds or "f" not in ds:
        return ds
    return ds.with_channels({"omega": np.asarray(ds["f"]) / frequency}, {"omega": "algebraic"})


def _rating(recs: Sequence[dict[str, Any]]) -> float:
    """The machine's rating guessed from the pre-fault apparent power (loaded to 80 %)."""
    s = np.mean([np.hypot(r["start"]["P"], r["start"]["Q"]) for r in recs]) / 0.8
    return max(float(s), 1e-3)


def _guess(family: Family, recs: Sequence[dict[str, Any]]) -> np.ndarray:
    """Typical values on the machine's own rating (`_rating`)."""
    s = _rating(recs)
    out = []
    for name in family.params:
        v = _TYPICAL[name]
        out.append(v / s if name in _IMPEDANCE else v * s if name == "M" else v)
    return np.asarray(out)


def _split_held_out(
    train: Sequence[Dataset], test: Sequence[Dataset] | None
) -> tuple[list[Dataset], list[Dataset], str]:
    if test:
        return list(train), list(test), f"{len(test)} held-out recording(s)"
    if len(train) > 1:
        return list(train[:-1]), [train[-1]], "the last recording, held out"
    raise ValueError(
        "a terminal diagnosis needs held-out data: give test recordings or two recordings"
    )


_SLOTS = 4  # coefficients a fit may free beside the family's parameters (one compilation)


class _Fit:
    """Levenberg-Marquardt on the output error (Marquardt's scaling): the family's parameters
    free and, with them, the coefficients of the chosen candidates (a block's gain with its
    time constant). One compiled Jacobian (forward mode through the simulation, `_SLOTS`
    columns beside the parameters, the unused ones switched off) serves every fit and the
    score test."""

    def __init__(self, sim: _Simulator, max_steps: int) -> None:
        self.sim, self.max_steps = sim, max_steps
        n_b = sim.n_base
        self.n_b = n_b

        def residual(full: jax.Array, weights: jax.Array) -> jax.Array:
            return sim.residual(full[:n_b], full[n_b:], weights)

        def jac(full: jax.Array, idx: jax.Array, active: jax.Array, weights: jax.Array):
            cols = jnp.concatenate([jnp.arange(n_b), n_b + idx])
            on = jnp.concatenate([jnp.ones(n_b), active])

            def res(phi: jax.Array) -> jax.Array:
                return residual(full.at[cols].add(phi * on), weights)

            m = n_b + _SLOTS
            return res(jnp.zeros(m)), jax.jacfwd(res)(jnp.zeros(m))

        self.residual = jax.jit(residual)
        self.jac = jax.jit(jac)

    def sse(self, full: np.ndarray, weights: jax.Array) -> float:
        r = np.asarray(self.residual(jnp.asarray(full), weights))
        return float(r @ r) if np.all(np.isfinite(r)) else float("inf")

    def _freed(self, ks: Sequence[int]) -> list[int]:
        out = []
        for k in ks:
            tau = self.sim.m.block(k)
            out += [k] if tau is None else [k, tau]
        return out

    def fits(self, ks: Sequence[int]) -> bool:
        """Whether candidates ``ks`` fit in the compiled Jacobian's `_SLOTS`."""
        return len(self._freed(ks)) <= _SLOTS

    def extra(self, ks: Sequence[int]) -> list[int]:
        """The coefficients freed with candidates ``ks``: each one's own, and a block's time
        constant after its gain."""
        if not self.fits(ks):
            raise ValueError(f"at most {_SLOTS} coefficients beside the parameters")
        return self._freed(ks)

    def jacobian(self, full: np.ndarray, ks: Sequence[int], weights: jax.Array):
        """Residual and Jacobian (the family's parameters, then the `extra` coefficients)."""
        extra = self.extra(ks)
        idx = np.asarray([*extra, *[0] * (_SLOTS - len(extra))])
        active = np.asarray([1.0] * len(extra) + [0.0] * (_SLOTS - len(extra)))
        r, J = self.jac(jnp.asarray(full), jnp.asarray(idx), jnp.asarray(active), weights)
        return np.asarray(r), np.asarray(J)[:, : self.n_b + len(extra)]

    def __call__(self, full: np.ndarray, ks: Sequence[int], weights: jax.Array) -> np.ndarray:
        """The fitted vector (the family's parameters, then every coefficient)."""
        full = np.asarray(full, dtype=float).copy()
        cols = [*range(self.n_b), *(self.n_b + e for e in self.extra(ks))]
        sse, lam = self.sse(full, weights), 1e-3
        if not np.isfinite(sse):
            return full
        for _ in range(self.max_steps):
            r, J = self.jacobian(full, ks, weights)
            A, g = J.T @ J, J.T @ r
            d = np.diag(A).copy()
            d = np.where(d > 0, d, 1.0)
            improved = converged = False
            while lam < 1e12:
                try:
                    step = -np.linalg.solve(A + lam * np.diag(d), g)
                except np.linalg.LinAlgError:
                    lam *= 4.0
                    continue
                trial = full.copy()
                trial[cols] += step
                new = self.sse(trial, weights)
                if np.isfinite(new) and new < sse:
                    improved = True
                    converged = sse - new <= 1e-10 * sse
                    full, sse, lam = trial, new, max(lam / 3.0, 1e-9)
                    break
                lam *= 4.0
            if not improved or converged:
                break
        return full

    def score(
        self, full: np.ndarray, chosen: Sequence[int], pool: Sequence[int], weights: jax.Array
    ) -> dict[int, float]:
        """First-order share of the sum of squares each candidate in ``pool`` removes, the
        family's parameters and the ``chosen`` coefficients refitted alongside:
        (g_k^T P r)^2 / (g_k^T P g_k) / r^T r with P the projection off their Jacobian (the
        score test of an omitted term)."""
        out: dict[int, float] = {}
        n_fixed = self.n_b + len(self.extra(chosen))
        q = pr = None
        rr = 1.0
        for k in pool:
            r, J = self.jacobian(full, [*chosen, k], weights)
            if q is None:
                Jb = J[:, :n_fixed]
                q, _ = np.linalg.qr(Jb / np.maximum(np.linalg.norm(Jb, axis=0), 1e-300))
                pr = r - q @ (q.T @ r)
                rr = max(float(r @ r), 1e-300)
            g = J[:, n_fixed]  # the candidate's own coefficient (a block's gain)
            pg = g - q @ (q.T @ g)
            den = float(pg @ pg)
            ok = den > 1e-10 * max(float(g @ g), 1e-300)
            out[k] = float(pg @ pr) ** 2 / den / rr if ok else 0.0
        return out

    def standard_errors(
        self, full: np.ndarray, ks: Sequence[int], weights: jax.Array
    ) -> np.ndarray:
        """Per column (the family's parameters, then the `extra` coefficients): the square
        roots of sigma^2 (J^T J)^-1, sigma^2 the residual variance per sample (white noise)."""
        r, J = self.jacobian(full, ks, weights)
        sigma2 = float(r @ r) / max(r.size - J.shape[1], 1)
        return np.sqrt(np.maximum(np.diag(sigma2 * np.linalg.pinv(J.T @ J)), 0.0))


def diagnose_terminal(
    train: Sequence[Dataset],
    family: str = "psat-5.1",
    *,
    test: Sequence[Dataset] | None = None,
    config: TerminalConfig | None = None,
    progress: Callable[[str], None] | None = None,
) -> TerminalDiagnosis:
    """Diagnose a built-in machine model from terminal channels (see the module docstring).

    ``train`` and ``test``: recordings with V, theta, P, Q (and optionally omega, P_m, v_f), on
    the machine's power base, events marked. Returns the verdict, the ranked candidates, the
    parameters before and after the extension and the errors of P and Q (and omega).
    ``progress`` receives a line after each stage (the fit is minutes on long data).
    """
    from jaxdmd.grid.machines import canonical_model_name

    def say(text: str) -> None:
        if progress is not None:
            progress(f"[{time.perf_counter() - started:6.1f} s] {text}")

    started = time.perf_counter()
    config = config or TerminalConfig()
    fam = FAMILIES[canonical_model_name(family)]
    train, held, held_text = _split_held_out(train, test)
    train = [_with_speed(ds, config.frequency) for ds in train]
    held = [_with_speed(ds, config.frequency) for ds in held]
    _check([*train, *held])
    every = [*train, *held]
    outputs = ("P", "Q", *(("omega",) if all("omega" in ds for ds in every) else ()))
    measured = tuple(u for u in fam.inputs if all(u in ds for ds in every))
    assumptions = tuple(
        f"{u} ({'the mechanical power' if u == 'P_m' else 'the field voltage'}) is not "
        "measured: assumed constant at its pre-fault equilibrium value"
        + (" (P_m = P_e before the fault)" if u == "P_m" else "")
        for u in fam.inputs
        if u not in measured
    )
    machine = _Machine(fam, 2.0 * np.pi * config.frequency, measured)
    recs = [_recording(ds, outputs, measured) for ds in train]
    sim = _Simulator(machine, recs, outputs, config.substeps)
    held_sim = _Simulator(
        machine, [_recording(ds, outputs, measured) for ds in held], outputs, config.substeps
    )
    n_b, n_c = len(fam.params), len(machine.cands)
    c0 = machine.c0()
    weights = jnp.ones(len(recs))
    fit = _Fit(sim, config.max_steps)

    # 1.-2. the refit, from typical values, with the reactances also halved and doubled
    typical = _guess(fam, recs)
    best: tuple[np.ndarray, float] | None = None
    origin = typical
    for factor in (1.0, 0.5, 2.0):
        start = np.asarray([v * factor if n in _IMPEDANCE else v for n, v in
                            zip(fam.params, typical, strict=True)])  # fmt: skip
        full = fit(np.concatenate([start, c0]), [], weights)
        sse = fit.sse(full, weights)
        if np.isfinite(sse) and (best is None or sse < best[1]):
            best, origin = (full, sse), start
    if best is None:
        raise ValueError(
            "the model does not simulate the training recordings from typical parameters"
        )
    refit, sse_refit = best
    say(f"refitted {fam.name} to the output error: NRMSE {np.sqrt(sse_refit):.3g} (root sum)")

    def held_error(full: np.ndarray) -> dict[str, float]:
        return held_sim.nrmse(held_sim.outputs_of(full))

    # 3. forward selection: every candidate ranked by the score test, the best few refitted in
    # full, the one that removes the largest share of the error left added if that share
    # reaches the threshold and the held-out recordings simulate better; then again
    chosen: list[int] = []
    steps: list[_Step] = []
    first: list[TerminalCandidate] = []
    current, sse_now, held_now = refit, sse_refit, held_error(refit)
    stopped = ""
    for _ in range(config.max_terms):
        pool = [k for k in range(n_c) if k not in chosen and fit.fits([*chosen, k])]
        if not pool:
            break
        scores = fit.score(current, chosen, pool, weights)
        order = sorted(pool, key=lambda k: -scores[k])
        ranked, fitted = [], {}
        for k in order[: config.refits]:
            # from the current model, and from the typical values it started at (a missing
            # effect may have pulled the refit far off: a constant field voltage under a
            # voltage regulator), and for a block also with a typical gain
            starts = [current, np.concatenate([origin, current[n_b:]])]
            if machine.cands[k][0] in _BLOCKS:
                typical_gain = starts[1].copy()
                typical_gain[n_b + k] = _TYPICAL_GAIN[machine.cands[k][0]](_rating(recs))
                starts.append(typical_gain)
            tries = [fit(s, [*chosen, k], weights) for s in starts]
            sses = [fit.sse(f, weights) for f in tries]
            fitted[k] = tries[int(np.argmin(sses))]
            share = float(1.0 - min(sses) / sse_now) if np.isfinite(min(sses)) else 0.0
            coefficient = float(fitted[k][n_b + k])
            ranked.append(TerminalCandidate(*machine.cands[k], scores[k], share, coefficient))
        # best first; candidates that fit alike (within 1e-6 of the error) are the same model
        # written two ways (e.g. either stator equation's reactance freed): the first in the
        # fixed candidate order is named, the others reported as equivalent
        ranked.sort(key=lambda c: (-round(c.explained or 0.0, 6), machine.cands.index(c.key)))
        if not first:
            rest = order[config.refits :]
            first = ranked + [TerminalCandidate(*machine.cands[k], scores[k]) for k in rest]
        pick = ranked[0] if ranked and (ranked[0].explained or 0.0) >= config.threshold else None
        if ranked:
            best_c = ranked[0]
            say(
                f"round {len(steps) + 1}: best {best_c.term} in {best_c.equation}, "
                f"{best_c.explained:.0%} of the error left"
            )
        if pick is None:
            break
        k = machine.cands.index(pick.key)
        held_new = held_error(fitted[k])
        if _mean_error(held_new) >= _mean_error(held_now):
            stopped = (
                f"{_adding(pick)} fits the training data better ({pick.explained:.0%} of the "
                "error left) but does not simulate the held-out data better"
            )
            break
        equivalent = [
            c for c in ranked[1:] if abs((c.explained or 0.0) - (pick.explained or 0.0)) <= 1e-6
        ]
        chosen.append(k)
        current, sse_now, held_now = fitted[k], fit.sse(fitted[k], weights), held_new
        se = fit.standard_errors(current, chosen, weights)
        steps.append(_Step(pick, tuple(equivalent), tuple(chosen), current, se))

    # 4. the gain on held-out data
    models = {"refit": (refit, [])}
    if chosen:
        models["extended"] = (current, chosen)
    errors: dict[str, dict[str, dict[str, float]]] = {"train": {}, "held_out": {}}
    params: dict[str, dict[str, float]] = {}
    ses: dict[str, dict[str, float]] = {}
    rolls: dict[str, list[np.ndarray]] = {}
    for name, (full, ks) in models.items():
        errors["train"][name] = sim.nrmse(sim.outputs_of(full))
        rolls[name] = held_sim.outputs_of(full)
        errors["held_out"][name] = held_sim.nrmse(rolls[name])
        named = _named(machine, fam, full, ks, fit.standard_errors(full, ks, weights))
        params[name] = {label: value for label, value, _ in named}
        ses[name] = {label: se for label, _, se in named}
    cause = _verdict(steps, stopped, first, errors, outputs, machine, fam, config)
    return TerminalDiagnosis(
        family=fam.name,
        cause=cause,
        candidates=tuple(first),
        parameters=params,
        standard_errors=ses,
        errors=errors,
        assumptions=assumptions,
        outputs=outputs,
        held_out=held_text,
        wall_time_s=time.perf_counter() - started,
        rollouts=rolls,
        measured=list(held_sim.y),
        times=[np.asarray(ds.t) for ds in held],
    )


@dataclass(frozen=True)
class _Step:
    """A term (or block) the forward selection added, with the model it gave."""

    pick: TerminalCandidate
    equivalent: tuple[TerminalCandidate, ...]
    ks: tuple[int, ...]  # every candidate chosen so far, this one last
    full: np.ndarray
    se: np.ndarray  # per column of the fit (`_Fit.standard_errors`)


def _adding(c: TerminalCandidate) -> str:
    """A candidate in words: "adding omega - 1 to the d omega/dt (swing)", "a governor ..."."""
    if c.equation in _BLOCKS:
        drive, what, *_ = _BLOCKS[c.equation]
        return f"{what} ({c.equation} driven by {drive})"
    return f"adding {c.term} to the {_LABELS[c.equation]}"


def _named(
    machine: _Machine, family: Family, full: np.ndarray, ks: Sequence[int], se: np.ndarray
) -> list[tuple[str, float, float]]:
    """Name, value and standard error of a fit's columns: the family's parameters, then per
    candidate its coefficient (``term in equation``, or a block's gain) and a block's time
    constant (from its inverse, which is fitted)."""
    n_b = len(family.params)
    out = [(n, float(full[i]), float(se[i])) for i, n in enumerate(family.params)]
    j = n_b
    for k in ks:
        eq, term = machine.cands[k]
        label = _BLOCKS[eq][2] if eq in _BLOCKS else f"{term} in {eq}"
        out.append((label, float(full[n_b + k]), float(se[j])))
        j += 1
        if eq in _BLOCKS:
            inv = float(full[n_b + machine.tau[eq]])
            out.append((_BLOCKS[eq][3], 1.0 / inv, float(se[j]) / inv**2))
            j += 1
    return out


def _step_summary(step: _Step, machine: _Machine, family: Family) -> str:
    pick = step.pick
    if pick.equation not in _BLOCKS:
        return (
            f"the {_LABELS[pick.equation]} lacks a term {pick.term}: adding it removes "
            f"{pick.explained:.0%} of the output error left on the training recordings"
            + "".join(
                f" ({_adding(c)} instead fits the same: the data cannot tell the two apart)"
                for c in step.equivalent
            )
        )
    u = pick.equation
    drive, what, gain, tname, _ = _BLOCKS[u]
    named = _named(machine, family, step.full, step.ks, step.se)
    value = {label: v for label, v, _ in named}
    se = {label: e for label, _, e in named}
    # standard errors above a tenth of the value: the data leave them loose
    loose = [n for n in (*family.params, gain) if se[n] > 0.1 * abs(value[n])]
    return (
        f"{u} ({_LABELS[u]}) is not constant: {what} ({tname} d{u}/dt = {u}_0 - {u} - {gain} "
        f"({drive})) with {gain} = {value[gain]:.4g} ± {se[gain]:.2g}, {tname} = "
        f"{value[tname]:.3g} s removes {pick.explained:.0%} of the output error left on the "
        "training recordings"
        + (
            f"; poorly determined by these data: {', '.join(loose)} (standard errors above "
            f"10 % of the values): measuring {u} would separate them"
            if loose
            else ""
        )
    )


def _verdict(
    steps: Sequence[_Step], stopped: str, first: Sequence[TerminalCandidate],
    errors: dict[str, dict[str, dict[str, float]]], outputs: Sequence[str],
    machine: _Machine, family: Family, config: TerminalConfig,
) -> dict[str, Any]:  # fmt: skip
    """The cause: the first term or block added (the largest), the others after it."""
    if not steps:
        if stopped:
            return {"kind": "none", "summary": f"{stopped}: no structural cause is named"}
        best = first[0].explained if first and first[0].explained is not None else 0.0
        return {
            "kind": "none",
            "summary": (
                f"no single term removes {config.threshold:.0%} of the refitted model's output "
                f"error (the best: {best:.0%}); the model agrees with the terminal data as far "
                "as they can tell"
            ),
        }
    head = steps[0].pick
    texts = [_step_summary(s, machine, family) for s in steps]
    then = "".join(f"; then {t}" for t in texts[1:])
    if stopped:
        then += f"; then {stopped}, and the selection stops"
    held = errors["held_out"]
    block = head.equation in _BLOCKS
    kind = "input" if block else "algebraic" if head.equation.startswith("stator") else "state"
    return {
        "kind": "missing variable" if block else "missing term",
        "equation": head.equation,
        "equation_kind": kind,
        "term": head.term,
        "explained": head.explained,
        "equivalent": [{"equation": c.equation, "term": c.term} for c in steps[0].equivalent],
        "further": [
            {"equation": s.pick.equation, "term": s.pick.term, "explained": s.pick.explained}
            for s in steps[1:]
        ],
        "summary": texts[0]
        + then
        + "; held-out NRMSE "
        + ", ".join(f"{o} {held['refit'][o]:.3g} -> {held['extended'][o]:.3g}" for o in outputs),
    }


def derived(family: str, p: dict[str, float]) -> dict[str, float]:
    """The familiar quantities from a family's fitted parameters: H = M / 2 [s] and the
    synchronous reactances (PSAT 5.1: x_q = c_e'd + c_e''d + x'_d, the equilibrium's relation)."""
    out = {"H": p["M"] / 2.0}
    if "x_d_minus_x_dp" in p:
        out["x_d"] = p["x_d_minus_x_dp"] + p["x_dp"]
    if family == "psat-5.1":
        out["x_q"] = p["c_edp"] + p["c_edpp"] + p["x_dp"]
    elif family == "two-axis":
        out["x_q"] = p["x_q_minus_x_qp"] + p["x_qp"]
    return out


def _mean_error(errors: dict[str, float]) -> float:
    return float(np.mean(list(errors.values())))


# ------------------------------------------------------------------------------------------------
# the report
# ------------------------------------------------------------------------------------------------


def write_terminal_report(out: str | Path, result: TerminalDiagnosis) -> Path:
    """``report.md``, ``diagnosis.json`` and ``terminal.png`` (held-out P, Q, omega measured
    and simulated) in ``out``; returns the report's path."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "diagnosis.json").write_text(json.dumps(result.to_dict(), indent=2) + "\n")
    _plot(out / "terminal.png", result)
    lines = [
        f"# Terminal-channel diagnosis: {result.family}",
        "",
        "The model was driven by the measured terminal voltage and angle; the rotor angle and "
        "internal voltages are latent states started at each recording's pre-fault "
        "equilibrium; the simulated "
        + ", ".join(result.outputs)
        + " are compared with the measured ones.",
        "",
        f"**Cause ({result.cause['kind']})**: {result.cause['summary']}",
        "",
    ]
    for a in result.assumptions:
        lines.append(f"- Not measured: {a}")
    if result.assumptions:
        lines.append("")
    lines += [
        f"## Output error (NRMSE; held out: {result.held_out})",
        "",
        "| model | data | " + " | ".join(result.outputs) + " |",
        "|---|---|" + "---|" * len(result.outputs),
    ]
    for where in ("train", "held_out"):
        for name, errs in result.errors[where].items():
            cells = " | ".join(f"{errs[o]:.4g}" for o in result.outputs)
            lines.append(f"| {name} | {where.replace('_', '-')} | {cells} |")
    lines += ["", "![held-out outputs](terminal.png)", "", "## Parameters", ""]
    lines += ["| parameter | " + " | ".join(result.parameters) + " |"]
    lines += ["|---|" + "---|" * len(result.parameters)]
    names = list(dict.fromkeys(n for p in result.parameters.values() for n in p))
    for n in names:
        cells = []
        for model, p in result.parameters.items():
            se = result.standard_errors.get(model, {}).get(n)
            v = p.get(n)
            text = "" if v is None else f"{v:.5g}" + (f" ± {se:.2g}" if se else "")
            if v is not None and se is not None and se > abs(v):
                text += " (not identified)"
            elif v is not None and se is not None and se > 0.1 * abs(v):
                text += " (poorly determined)"
            cells.append(text)
        lines.append(f"| {n} | " + " | ".join(cells) + " |")
    for model, p in result.parameters.items():
        d = derived(result.family, p)
        lines.append(f"\n{model}: " + ", ".join(f"{k} = {v:.5g}" for k, v in d.items()))
    lines += [
        "",
        "## Candidates (score test, then the best refitted)",
        "",
        "| equation | term | score | explained when refitted |",
        "|---|---|---|---|",
    ]
    for c in result.candidates[:12]:
        expl = "" if c.explained is None else f"{c.explained:.1%}"
        lines.append(f"| {_LABELS[c.equation]} | {c.term} | {c.score:.1%} | {expl} |")
    path = out / "report.md"
    path.write_text("\n".join(lines) + "\n")
    return path


def _plot(path: Path, result: TerminalDiagnosis) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n_o = len(result.outputs)
    fig, axes = plt.subplots(n_o, 1, figsize=(8, 2.2 * n_o), sharex=True)
    axes = np.atleast_1d(axes)
    t, y = result.times[0], result.measured[0]
    for j, (ax, o) in enumerate(zip(axes, result.outputs, strict=True)):
        ax.plot(t, y[j], color="k", lw=1.0, label="measured")
        for name, runs in result.rollouts.items():
            ax.plot(t, runs[0][j], lw=1.0, ls="--" if name == "refit" else "-", label=name)
        ax.set_ylabel(o)
    axes[0].legend(loc="best", fontsize=8)
    axes[-1].set_xlabel("t [s]")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
