"""Per-generator datasets and the paper's experiment (training fault at bus 15, test at bus 28)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jaxdmd.grid.machines import STATE_LAYOUT, MachineModel, as_model
from jaxdmd.grid.network import case39
from jaxdmd.grid.operating import OperatingPoint, operating_points
from jaxdmd.grid.simulate import (
    DEFAULT_SETTINGS,
    Fault,
    SimResult,
    SolverSettings,
    out_of_step,
    simulate,
    warn_out_of_step,
)

ALGEBRAIC_CHANNELS = ("i_d", "i_q", "P_e", "Q_e", "v_d", "v_q")
INPUT_CHANNELS = ("P_m", "v_f")
BOUNDARY_CHANNELS = ("V", "theta")
UNITS = {"delta": "rad", "theta": "rad", "omega": "pu"}


def generator_channels(
    result: SimResult, generator: int, index: int | None = None
) -> tuple[dict[str, np.ndarray], dict[str, str], dict[str, str], dict[str, np.ndarray]]:
    """Channels of one generator of one run, as NumPy arrays.

    Args:
        result: a simulation (single run, or a batch with ``index`` selecting the run).
        generator: generator bus number (30..39).
        index: run index for a batched result.

    Returns:
        ``(channels, roles, units, derivatives)``: states of the model (role ``state``),
        ``i_d i_q P_e Q_e v_d v_q`` (``algebraic``), ``P_m v_f`` (``input``), ``V theta``
        (``boundary``); ``derivatives`` holds the exact state derivatives.
    """
    g = case39().gen_index(generator)
    batched = result.x.ndim == 4
    if batched and index is None:
        raise ValueError("a batched SimResult needs index=")
    sel = (lambda a: np.asarray(a[index])) if batched else np.asarray
    x, dx = sel(result.x), sel(result.dx)
    channels: dict[str, np.ndarray] = {}
    roles: dict[str, str] = {}
    derivs: dict[str, np.ndarray] = {}
    for s in result.model.states:
        k = STATE_LAYOUT.index(s)
        channels[s], derivs[s], roles[s] = x[:, k, g], dx[:, k, g], "state"
    for names, role in (
        (ALGEBRAIC_CHANNELS, "algebraic"),
        (INPUT_CHANNELS, "input"),
        (BOUNDARY_CHANNELS, "boundary"),
    ):
        for nm in names:
            channels[nm], roles[nm] = sel(result.alg[nm])[:, g], role
    units = {nm: UNITS.get(nm, "pu") for nm in channels}
    return channels, roles, units, derivs


def generator_dataset(
    result: SimResult,
    generator: int,
    index: int | None = None,
    *,
    noise: float = 0.0,
    key: jax.Array | None = None,
    label: str = "",
):
    """A :class:`jaxdmd.data.Dataset` for one generator of one run.

    Without noise the exact state derivatives are attached. With ``noise > 0`` Gaussian noise of
    sigma = ``noise`` x (max - min) of each state channel over the record is added to the states
    only (``key`` required) and the derivatives are estimated from the noisy states by
    ``Dataset.create``; the exact ones are in :func:`generator_channels`.
    """
    from jaxdmd.data import Dataset

    channels, roles, units, derivs = generator_channels(result, generator, index)
    if noise < 0:
        raise ValueError(f"noise must be >= 0, got {noise}")
    exact: dict[str, np.ndarray] | None = derivs
    if noise > 0:
        if key is None:
            raise ValueError("noise > 0 needs a PRNG key")
        states = [nm for nm in channels if roles[nm] == "state"]
        z = np.asarray(jax.random.normal(key, (len(result.t), len(states)), jnp.float64))
        for j, nm in enumerate(states):
            channels[nm] = channels[nm] + noise * np.ptp(channels[nm]) * z[:, j]
        exact = None
    events = result.fault.events if result.fault is not None else ()
    return Dataset.create(
        np.asarray(result.t), channels, roles, units=units, derivatives=exact, events=events,
        label=label,
    )  # fmt: skip


@dataclass
class ProtocolData:
    """Output of :func:`paper_protocol`, keyed by generator bus number.

    Attributes:
        train: noisy bus-15-fault datasets (derivatives estimated from the noisy states).
        test: clean bus-28-fault datasets with exact derivatives.
        train_clean: the training runs without noise, with exact derivatives.
        train_exact_derivatives: exact state derivatives of the training runs (dicts).
        train_points, test_points: the operating points (stacked; None for a part not made).
        train_result, test_result: the raw batched simulations (None for a part not made).
        out_of_step: ``{"train": [...], "test": [...]}``, per run the generators (bus numbers)
            that lose synchronism (see :func:`jaxdmd.grid.simulate.out_of_step`); empty tuples
            for a stable run. :func:`paper_protocol` warns when any is not empty.
    """

    train: dict[int, list]
    test: dict[int, list]
    train_clean: dict[int, list]
    train_exact_derivatives: dict[int, list[dict[str, np.ndarray]]]
    train_points: OperatingPoint | None
    test_points: OperatingPoint | None
    train_result: SimResult | None
    test_result: SimResult | None
    config: dict = field(default_factory=dict)
    out_of_step: dict[str, list[tuple[int, ...]]] = field(default_factory=dict)

    @property
    def stable(self) -> bool:
        """Whether every machine stays in step in every run."""
        return not any(gens for runs in self.out_of_step.values() for gens in runs)


def simulate_each(ops: OperatingPoint, model, fault, *, warn: bool = True, **kw) -> SimResult:
    """Simulate stacked operating points one by one and stack the results like a vmapped run.

    A loop, not ``vmap``: the batched diffrax solve gives no speed-up here (every run of a batch
    takes the union of all runs' steps) and, on jax 0.10.2's CPU runtime, the vmapped execution
    now and then never signals completion (a hang at 0 % CPU, about one run in four).
    """
    runs = [simulate(ops[i], model, fault, warn=False, **kw) for i in range(ops.Vm.shape[0])]
    stacked = jax.tree.map(lambda *xs: jnp.stack(xs), *runs)
    result = eqx.tree_at(lambda r: r.t, stacked, runs[0].t)
    if warn:
        names = [f"run {i} (fault bus {result.fault.bus})" for i in range(len(runs))]
        warn_out_of_step(out_of_step(result), names)
    return result


def paper_protocol(
    n_train: int = 4,
    n_test: int = 4,
    seed: int = 0,
    noise: float = 0.01,
    model: MachineModel | str = "psat-5.1",
    *,
    generators: Sequence[int] | None = None,
    train_fault: Fault | int = 15,
    test_fault: Fault | int = 28,
    spread: float = 0.3,
    t_end: float = 10.0,
    dt: float = 0.01,
    settings: SolverSettings = DEFAULT_SETTINGS,
    parts: Sequence[str] = ("train", "test"),
) -> ProtocolData:
    """The paper's experiment in one call.

    ``n_train + n_test`` operating points (loads uniform within +-``spread`` per bus, OPF
    dispatch; the first ``n_train`` for training) are drawn from ``seed``; every point is
    simulated for ``t_end`` s with a fault at ``train_fault`` (training) or ``test_fault``
    (test). The training states get Gaussian noise with sigma = ``noise`` x (max - min) of each
    state signal over the record, from ``jax.random.key(seed)``; test data stay clean. A run in
    which a machine loses synchronism gives a :class:`~jaxdmd.grid.simulate.SynchronismWarning`
    naming the recordings and generators (and ``ProtocolData.out_of_step``).

    Args:
        generators: generator buses to return (default all ten, 30..39).
        parts: ``("train",)`` or ``("test",)`` computes that part alone (the other's lists are
            empty, its points and result None): the same recordings as both together, since
            every operating point and noise draw depends on the seed and its index alone.
    """
    case = case39()
    gens = tuple(case.gen_bus_numbers if generators is None else (int(g) for g in generators))
    for gb in gens:
        case.gen_index(gb)
    if n_train < 1 or n_test < 0:
        raise ValueError(f"need n_train >= 1 and n_test >= 0, got {n_train}, {n_test}")
    if not parts or set(parts) - {"train", "test"}:
        raise ValueError(f"parts must be 'train' and/or 'test', got {tuple(parts)}")
    model = as_model(model)
    tf = train_fault if isinstance(train_fault, Fault) else Fault(bus=int(train_fault))
    sf = test_fault if isinstance(test_fault, Fault) else Fault(bus=int(test_fault))
    n_train_here = n_train if "train" in parts else 0
    n_test_here = n_test if "test" in parts else 0
    kw = dict(t_end=t_end, dt=dt, settings=settings)
    train_ops = r_train = test_ops = r_test = None
    if n_train_here:
        train_ops = operating_points(n_train, seed, spread=spread)
        r_train = simulate_each(train_ops, model, tf, warn=False, **kw)
    if n_test_here:
        test_ops = operating_points(n_test, seed, spread=spread, first=n_train)
        r_test = simulate_each(test_ops, model, sf, warn=False, **kw)
    slipped = {
        "train": out_of_step(r_train) if n_train_here else [],
        "test": out_of_step(r_test) if n_test_here else [],
    }
    warn_out_of_step(
        [*slipped["train"], *slipped["test"]],
        [
            *(f"train point {i} (seed {seed}, fault bus {tf.bus})" for i in range(n_train_here)),
            *(f"test point {i} (seed {seed}, fault bus {sf.bus})" for i in range(n_test_here)),
        ],
    )
    noise_key = jax.random.fold_in(jax.random.key(seed), 0x5EED)
    train, clean, exact, test = {}, {}, {}, {}
    for gb in gens:
        train[gb], clean[gb], exact[gb], test[gb] = [], [], [], []
        for i in range(n_train_here):
            lab = f"case39 gen {gb}, {model.name}, fault bus {tf.bus}, train point {i}"
            k = jax.random.fold_in(jax.random.fold_in(noise_key, i), gb)
            clean[gb].append(generator_dataset(r_train, gb, i, label=lab))
            exact[gb].append(generator_channels(r_train, gb, i)[3])
            train[gb].append(
                generator_dataset(r_train, gb, i, noise=noise, key=k, label=lab + ", noisy")
                if noise > 0
                else clean[gb][-1]
            )
        for i in range(n_test_here):
            lab = f"case39 gen {gb}, {model.name}, fault bus {sf.bus}, test point {i}"
            test[gb].append(generator_dataset(r_test, gb, i, label=lab))
    config = dict(
        n_train=n_train, n_test=n_test, seed=seed, noise=noise, model=model,
        train_fault=tf, test_fault=sf, spread=spread, t_end=t_end, dt=dt,
    )  # fmt: skip
    return ProtocolData(
        train, test, clean, exact, train_ops, test_ops, r_train, r_test, config, slipped
    )
