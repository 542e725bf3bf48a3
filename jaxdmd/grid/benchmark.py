"""The built-in benchmark: the paper's protocol as ``python -m jaxdmd.run`` and Table I run it."""

from __future__ import annotations

from collections.abc import Sequence

from jaxdmd.grid.machines import Exciter, Governor, MachineModel
from jaxdmd.grid.protocol import ProtocolData, paper_protocol

__all__ = ["benchmark_protocol"]


def benchmark_protocol(
    generators: Sequence[int] = (31,),
    operating_points: int = 4,
    noise: float = 0.01,
    seed: int = 0,
    parts: Sequence[str] = ("train", "test"),
) -> ProtocolData:
    """The paper's protocol for the benchmark generators: noisy bus-15 training, clean bus-28
    test data, ``operating_points`` of each, from ``seed``.

    The machines are PSAT model 5.1 with the simple exciter and governor of ``jaxdmd.grid``
    (the paper's "exogenous inputs from the prime mover and AVR"): without them the whole system
    keeps accelerating after the fault (D = 0, constant-impedance loads; omega reaches 1.03 pu,
    delta 60 rad), and noise of 1 % of each signal's range then buries the dynamics. The training
    derivatives are the default estimates from the noisy states (matched fitting applies).
    ``parts``: as :func:`paper_protocol`'s (one part alone, the same recordings).
    """
    return paper_protocol(
        n_train=operating_points,
        n_test=operating_points,
        seed=seed,
        noise=noise,
        model=MachineModel(name="psat-5.1", exciter=Exciter(), governor=Governor()),
        generators=tuple(generators),
        parts=parts,
    )
