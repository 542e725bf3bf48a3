"""IEEE 39-bus network: MATPOWER ``case39`` data, admittance matrix and a Newton power flow in JAX.

The network data are PYPOWER's copy of MATPOWER ``case39`` (100 MVA base, 60 Hz). Buses are
numbered 1..39 externally (as in the case file) and 0..38 internally. The admittance matrix is
built as MATPOWER's ``makeYbus`` builds it (pi branches, off-nominal tap ratio and phase shift on
the "from" side, bus shunts). The power flow is a full Newton-Raphson iteration on the polar
mismatch equations, written in JAX (float64), jit-able and vmap-able over injections.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

BASE_MVA = 100.0
FREQUENCY_HZ = 60.0
OMEGA_B = 2.0 * np.pi * FREQUENCY_HZ

PQ, PV, REF = 1, 2, 3


@dataclass(frozen=True, eq=False)
class Case:
    """Static network data (NumPy, never traced).

    Attributes:
        bus_numbers: external bus numbers, shape (nb,).
        bus_type: MATPOWER bus types (1 PQ, 2 PV, 3 reference), shape (nb,).
        Pd, Qd: nominal loads in pu on ``BASE_MVA``, shape (nb,).
        Gs, Bs: bus shunts in pu, shape (nb,).
        Y: complex bus admittance matrix in pu, shape (nb, nb), loads not included.
        gen_bus: internal index of each generator's bus, shape (ng,).
        Pg, Qg, Vg: case-file dispatch (pu) and voltage set points, shape (ng,).
        Pmax: generator active power limits in pu, shape (ng,).

    Equality and hashing are by identity (a Case is a static argument under jit).
    """

    bus_numbers: np.ndarray
    bus_type: np.ndarray
    Pd: np.ndarray
    Qd: np.ndarray
    Gs: np.ndarray
    Bs: np.ndarray
    Y: np.ndarray
    gen_bus: np.ndarray
    Pg: np.ndarray
    Qg: np.ndarray
    Vg: np.ndarray
    Pmax: np.ndarray

    @property
    def n_bus(self) -> int:
        return len(self.bus_numbers)

    @property
    def n_gen(self) -> int:
        return len(self.gen_bus)

    @property
    def gen_bus_numbers(self) -> tuple[int, ...]:
        return tuple(int(self.bus_numbers[i]) for i in self.gen_bus)

    @property
    def ref_bus(self) -> int:
        return int(np.flatnonzero(self.bus_type == REF)[0])

    def bus_index(self, bus: int) -> int:
        """Internal index of external bus number ``bus``; ``ValueError`` if there is none."""
        hits = np.flatnonzero(self.bus_numbers == int(bus))
        if hits.size == 0:
            raise ValueError(
                f"unknown bus {bus!r}: the IEEE 39-bus system has buses "
                f"{int(self.bus_numbers.min())}..{int(self.bus_numbers.max())}"
            )
        return int(hits[0])

    def gen_index(self, bus: int) -> int:
        """Index (0..9) of the generator at external bus ``bus``; ``ValueError`` if none."""
        hits = [k for k, b in enumerate(self.gen_bus_numbers) if b == int(bus)]
        if not hits:
            raise ValueError(
                f"no generator at bus {bus!r}: generators are at buses {list(self.gen_bus_numbers)}"
            )
        return hits[0]


def make_ybus(ppc: dict) -> np.ndarray:
    """Complex bus admittance matrix of a MATPOWER/PYPOWER case, as MATPOWER's ``makeYbus``."""
    bus, branch = np.asarray(ppc["bus"], float), np.asarray(ppc["branch"], float)
    base = float(ppc["baseMVA"])
    nb = bus.shape[0]
    index = {int(b): i for i, b in enumerate(bus[:, 0])}
    on = branch[:, 10] > 0
    br = branch[on]
    f = np.array([index[int(b)] for b in br[:, 0]])
    t = np.array([index[int(b)] for b in br[:, 1]])
    ys = 1.0 / (br[:, 2] + 1j * br[:, 3])
    bc = br[:, 4]
    tap = np.where(br[:, 8] == 0.0, 1.0, br[:, 8]) * np.exp(1j * np.deg2rad(br[:, 9]))
    ytt = ys + 1j * bc / 2
    yff = ytt / (tap * np.conj(tap))
    yft = -ys / np.conj(tap)
    ytf = -ys / tap
    Y = np.zeros((nb, nb), complex)
    np.add.at(Y, (f, f), yff)
    np.add.at(Y, (t, t), ytt)
    np.add.at(Y, (f, t), yft)
    np.add.at(Y, (t, f), ytf)
    Y[np.diag_indices(nb)] += (bus[:, 4] + 1j * bus[:, 5]) / base
    return Y


def case_from_ppc(ppc: dict) -> Case:
    """Build a :class:`Case` from a PYPOWER case dict (one generator per generator bus)."""
    bus, gen = np.asarray(ppc["bus"], float), np.asarray(ppc["gen"], float)
    base = float(ppc["baseMVA"])
    index = {int(b): i for i, b in enumerate(bus[:, 0])}
    gen = gen[gen[:, 7] > 0]
    gen_bus = np.array([index[int(b)] for b in gen[:, 0]])
    if len(set(gen_bus.tolist())) != len(gen_bus):
        raise ValueError("one generator per bus is required")
    return Case(
        bus_numbers=bus[:, 0].astype(int),
        bus_type=bus[:, 1].astype(int),
        Pd=bus[:, 2] / base,
        Qd=bus[:, 3] / base,
        Gs=bus[:, 4] / base,
        Bs=bus[:, 5] / base,
        Y=make_ybus(ppc),
        gen_bus=gen_bus,
        Pg=gen[:, 1] / base,
        Qg=gen[:, 2] / base,
        Vg=gen[:, 5],
        Pmax=gen[:, 8] / base,
    )


@functools.cache
def case39() -> Case:
    """The IEEE 39-bus (New England) system from PYPOWER's copy of MATPOWER ``case39``."""
    from pypower.case39 import case39 as _ppc39

    return case_from_ppc(_ppc39())


def power_injection(Y: jax.Array, Vm: jax.Array, Va: jax.Array) -> jax.Array:
    """Complex bus injections S = V conj(Y V) for polar voltages."""
    V = Vm * jnp.exp(1j * Va)
    return V * jnp.conj(Y @ V)


def newton_pf(
    case: Case,
    Pg: jax.Array,
    Vg: jax.Array,
    Pd: jax.Array,
    Qd: jax.Array,
    *,
    tol: float = 1e-12,
    max_iter: int = 30,
) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array]:
    """Newton-Raphson power flow (polar), jit-able and vmap-able over injections.

    The reference bus keeps angle 0 and its generator's voltage set point; PV buses keep their
    generator's set point (reactive limits are not enforced, as PYPOWER's default). The
    reference generator's ``Pg`` entry is ignored and returned as solved.

    Args:
        case: static network data.
        Pg: generator active powers in pu, shape (ng,).
        Vg: generator voltage set points in pu, shape (ng,).
        Pd, Qd: bus loads in pu (constant power during the power flow), shape (nb,).
        tol: infinity-norm tolerance on the power mismatch in pu.
        max_iter: iteration limit.

    Returns:
        ``(Vm, Va, Pg, Qg)``: bus voltage magnitudes and angles (rad), shape (nb,), and the
        generators' active and reactive powers in pu, shape (ng,). ``Vm`` is NaN if the
        iteration did not converge.
    """
    Y = jnp.asarray(case.Y)
    nb = case.n_bus
    gb = jnp.asarray(case.gen_bus)
    is_pq = jnp.asarray(case.bus_type == PQ)
    is_ref = jnp.asarray(case.bus_type == REF)
    Pg = jnp.asarray(Pg, jnp.float64)
    Vg = jnp.asarray(Vg, jnp.float64)
    Psch = jnp.zeros(nb).at[gb].add(Pg) - Pd
    Qd = jnp.asarray(Qd, jnp.float64)
    Vset = jnp.ones(nb).at[gb].set(Vg)

    def residual(x: jax.Array) -> jax.Array:
        Va, Vm = x[:nb], x[nb:]
        S = power_injection(Y, Vm, Va)
        rp = jnp.where(is_ref, Va, S.real - Psch)
        rq = jnp.where(is_pq, S.imag + Qd, Vm - Vset)
        return jnp.concatenate([rp, rq])

    jac = jax.jacfwd(residual)

    def cond(carry):
        x, k = carry
        return (jnp.max(jnp.abs(residual(x))) > tol) & (k < max_iter)

    def body(carry):
        x, k = carry
        return x - jnp.linalg.solve(jac(x), residual(x)), k + 1

    x0 = jnp.concatenate([jnp.zeros(nb), Vset])
    x, _ = jax.lax.while_loop(cond, body, (x0, 0))
    ok = jnp.max(jnp.abs(residual(x))) <= tol * 10
    Va, Vm = x[:nb], jnp.where(ok, x[nb:], jnp.nan)
    S = power_injection(Y, Vm, Va)
    Sg = S[gb] + (Pd + 1j * Qd)[gb]
    return Vm, Va, Sg.real, Sg.imag


def kron_reduce(Y: jax.Array, keep: np.ndarray) -> tuple[jax.Array, jax.Array]:
    """Kron-reduce a bus admittance matrix onto the buses ``keep``.

    Returns ``(Y_red, W)``: the reduced matrix (len(keep) square) and the reconstruction matrix
    ``W`` (nb x len(keep)) with ``V_all = W @ V_keep`` when no current enters the other buses.
    """
    nb = Y.shape[0]
    keep = np.asarray(keep)
    drop = np.setdiff1d(np.arange(nb), keep)
    Ykk = Y[np.ix_(keep, keep)]
    Ykd = Y[np.ix_(keep, drop)]
    Ydk = Y[np.ix_(drop, keep)]
    Ydd = Y[np.ix_(drop, drop)]
    X = jnp.linalg.solve(Ydd, Ydk)
    Y_red = Ykk - Ykd @ X
    W = jnp.zeros((nb, len(keep)), Y.dtype).at[keep].set(jnp.eye(len(keep))).at[drop].set(-X)
    return Y_red, W
