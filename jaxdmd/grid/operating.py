"""Operating points of the IEEE 39-bus system: randomly scaled loads, OPF dispatch, Newton PF.

Each operating point scales every bus load (P and Q alike) by its own factor drawn uniformly from
``[1 - spread, 1 + spread]`` (default spread 0.3, the paper's +-30 %) with a JAX PRNG key derived
from an integer seed. PYPOWER's ``runopf`` (printing suppressed) dispatches the generators; the JAX
Newton power flow then solves the network with the OPF's active powers and voltage set points,
so that the operating point is exactly consistent with this package's network model. A draw whose
OPF fails is replaced by a fresh draw from the next key (``fold_in(key, attempt)``), so the result
is a deterministic function of ``(n, seed, spread)``.
"""

from __future__ import annotations

import contextlib
import io

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jaxdmd.grid.network import BASE_MVA, Case, case39, newton_pf


class OperatingPoint(eqx.Module):
    """A solved power flow. Arrays may carry a leading batch axis (a stack of points).

    Attributes:
        Vm: bus voltage magnitudes (pu), shape (..., 39).
        Va: bus voltage angles (rad), reference bus 31 at 0, shape (..., 39).
        Pg, Qg: generator injections (pu on 100 MVA), shape (..., 10), buses 30..39 in order.
        Pd, Qd: bus loads (pu), shape (..., 39).
        load_factors: the per-bus load scaling factors, shape (..., 39).
    """

    Vm: jax.Array
    Va: jax.Array
    Pg: jax.Array
    Qg: jax.Array
    Pd: jax.Array
    Qd: jax.Array
    load_factors: jax.Array

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return tuple(self.Vm.shape[:-1])

    def __len__(self) -> int:
        if not self.batch_shape:
            raise TypeError("a single OperatingPoint has no length")
        return self.batch_shape[0]

    def __getitem__(self, i) -> OperatingPoint:
        return jax.tree_util.tree_map(lambda a: a[i], self)


_pf_jit = jax.jit(newton_pf, static_argnums=0)


def _solve(case: Case, Pg, Vg, Pd, Qd, factors) -> OperatingPoint:
    Vm, Va, Pg_, Qg = _pf_jit(
        case, jnp.asarray(Pg), jnp.asarray(Vg), jnp.asarray(Pd), jnp.asarray(Qd)
    )
    if not bool(jnp.all(jnp.isfinite(Vm))):
        raise RuntimeError("the Newton power flow did not converge for this operating point")
    return OperatingPoint(Vm, Va, Pg_, Qg, jnp.asarray(Pd), jnp.asarray(Qd), jnp.asarray(factors))


def nominal_operating_point(case: Case | None = None) -> OperatingPoint:
    """The case-file operating point: nominal loads, the case file's dispatch and set points."""
    case = case or case39()
    ones = np.ones(case.n_bus)
    return _solve(case, case.Pg, case.Vg, case.Pd, case.Qd, ones)


def opf_operating_point(factors, case: Case | None = None) -> OperatingPoint:
    """Operating point for per-bus load factors (shape (39,) or a scalar): PYPOWER OPF + JAX PF.

    Raises ``RuntimeError`` if the OPF fails.
    """
    from pypower.api import ppoption, runopf
    from pypower.case39 import case39 as ppc39

    case = case or case39()
    factors = np.broadcast_to(np.asarray(factors, float), (case.n_bus,)).copy()
    ppc = ppc39()
    ppc["bus"][:, 2] *= factors
    ppc["bus"][:, 3] *= factors
    with contextlib.redirect_stdout(io.StringIO()):
        r = runopf(ppc, ppoption(VERBOSE=0, OUT_ALL=0))
    if not r["success"]:
        raise RuntimeError(f"PYPOWER runopf failed for load factors {factors.round(3).tolist()}")
    on = r["gen"][:, 7] > 0
    Pg = r["gen"][on, 1] / BASE_MVA
    Vg = r["bus"][case.gen_bus, 7]
    return _solve(case, Pg, Vg, case.Pd * factors, case.Qd * factors, factors)


def load_factors(key: jax.Array, n: int, n_bus: int = 39, spread: float = 0.3) -> jax.Array:
    """Per-bus load factors uniform in ``[1 - spread, 1 + spread]``, shape (n, n_bus)."""
    return jax.random.uniform(key, (n, n_bus), jnp.float64, 1.0 - spread, 1.0 + spread)


def operating_points(
    n: int,
    seed: int | jax.Array = 0,
    *,
    spread: float = 0.3,
    max_attempts: int = 5,
    first: int = 0,
) -> OperatingPoint:
    """``n`` random operating points, stacked along a leading axis; reproducible from ``seed``.

    Point ``i`` depends on ``seed`` and ``i`` alone: ``operating_points(n, seed, first=k)`` are
    points ``k`` to ``k + n - 1`` of any longer draw from the same seed.

    Args:
        n: number of operating points (>= 1).
        seed: integer seed or a JAX PRNG key.
        spread: loads vary within ``+-spread`` of nominal (0.3 in the paper).
        max_attempts: redraws allowed per point when the OPF fails.
        first: the index of the first point.
    """
    if n < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    if first < 0:
        raise ValueError(f"first must be >= 0, got {first}")
    if not 0.0 <= spread < 1.0:
        raise ValueError(f"spread must be in [0, 1), got {spread}")
    case = case39()
    key = jax.random.key(seed) if isinstance(seed, int) else seed
    points = []
    for i in range(first, first + n):
        for attempt in range(max_attempts):
            k = jax.random.fold_in(jax.random.fold_in(key, i), attempt)
            f = np.asarray(load_factors(k, 1, case.n_bus, spread)[0])
            try:
                points.append(opf_operating_point(f, case))
                break
            except RuntimeError:
                continue
        else:
            raise RuntimeError(
                f"no feasible operating point after {max_attempts} draws (point {i})"
            )
    return jax.tree_util.tree_map(lambda *a: jnp.stack(a), *points)
