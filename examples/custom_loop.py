"""A custom search loop on the public API: ``prompts`` -> a proposer -> ``step``.

The data hide an effect the starting model lacks: the speed equation of a machine needs the
electrical power P_e, which the variable library does not hold at first. The loop below prints
every round, stops early once the score is good enough for us, and shows the final equations.

    python examples/custom_loop.py [--rounds N] [--operating-points N]
"""

from __future__ import annotations

import argparse

import jax

import jaxdmd
from jaxdmd import search
from jaxdmd.grid import Exciter, Governor, MachineModel, paper_protocol
from jaxdmd.problems import de_problem
from jaxdmd.proposers.offline import OfflineProposer


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=8)
    parser.add_argument("--operating-points", type=int, default=2)
    args = parser.parse_args()

    # measured data: generator 31 of the IEEE 39-bus system, noisy states, bus-15 fault
    model = MachineModel(name="psat-5.1", exciter=Exciter(), governor=Governor())
    data = paper_protocol(n_train=args.operating_points, n_test=0, model=model, generators=(31,))
    recordings = [ds.with_estimated_derivatives(smooth=True) for ds in data.train[31]]

    # only the swing equation (delta, omega) this time: select the two states' problem
    problem, contract = de_problem([ds.select(_swing_channels(ds)) for ds in recordings])
    config = search.SearchConfig(
        n_islands=4, prompts_per_round=2, samples_per_prompt=4, max_rounds=args.rounds
    )
    state = search.init(problem, contract, jax.random.key(0), config)
    proposer = OfflineProposer.for_problem(problem)

    while not state.done:
        state, requests = search.prompts(state)  # pure: in-context examples from the islands
        samples = proposer.propose(requests)  # any proposer: offline, an LLM, your own
        state, report = search.step(state, samples)  # pure: check, compile, fit, register
        library = ", ".join(v.name for v in state.contract.library) or "-"
        print(f"round {report.round}: best {report.best_score:.4g}, library [{library}]")
        if report.best_score > -0.02:  # our own stopping rule on top of the paper's
            break

    for lhs, rhs in search.final_equations(state).readable().items():
        print(f"{lhs} = {rhs}")


def _swing_channels(ds: jaxdmd.data.Dataset) -> list[str]:
    return [n for n in ds.names if ds.role(n) != "state" or n in ("delta", "omega")]


if __name__ == "__main__":
    main()
