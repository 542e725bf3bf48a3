"""Diagnose models on data with effects the tests do not use; print one JSON line per case.

    python benchmarks/diagnose_effects.py [--cases exciter psat-damping psat-none] [--noise 0.005]

Each case simulates the IEEE 39-bus system (generator 31; three bus-15-fault recordings for
training with noise, one clean bus-28-fault recording held out) with an effect, and diagnoses
a model that lacks it (the truth is here, in the benchmark, not in the engine):

- ``exciter``: an AVR moves v_f; the model (a file) has a one-axis machine with constant v_f;
- ``psat-damping``: D = 10 in PSAT 5.1 with AVR and governor; the built-in psat-5.1 model;
- ``psat-none``: PSAT 5.1 with AVR and governor, no hidden effect; the built-in psat-5.1.
"""

from __future__ import annotations

import argparse
import json
import time

import jax

from jaxdmd.diagnose import builtin_model, diagnose, parse_model
from jaxdmd.grid import Exciter, Governor, MachineModel, paper_protocol

CONSTANT_VF = (
    "def equation(omega, e_qp, P_m, P_e, i_d, p):\n"
    "    d_delta = p[0] * (omega - 1)\n"
    "    d_omega = p[1] * P_m + p[2] * P_e\n"
    "    d_e_qp = p[3] + p[4] * e_qp + p[5] * i_d  # v_f constant\n"
    "    return d_delta, d_omega, d_e_qp\n"
)


def case(name: str):
    controls = {"exciter": Exciter(), "governor": Governor()}
    if name == "exciter":
        truth = MachineModel(name="one-axis", exciter=Exciter())
        return truth, parse_model(CONSTANT_VF, "constant-vf.py", ("delta", "omega", "e_qp"))
    if name == "psat-damping":
        return MachineModel(name="psat-5.1", damping=10.0, **controls), builtin_model("psat-5.1")
    if name == "psat-none":
        return MachineModel(name="psat-5.1", **controls), builtin_model("psat-5.1")
    raise ValueError(f"unknown case {name!r}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", nargs="+", default=["exciter", "psat-damping", "psat-none"])
    parser.add_argument("--noise", type=float, default=0.005)
    args = parser.parse_args()
    for name in args.cases:
        start = time.perf_counter()
        truth, model = case(name)
        data = paper_protocol(n_train=3, n_test=1, noise=args.noise, model=truth, generators=[31])
        result = diagnose(list(data.train[31]), model, test=data.test[31], key=jax.random.key(0))
        row = {
            "case": name,
            "model": model.name,
            "cause": result.cause.to_dict(),
            "nrmse_before": result.metrics.get("given", result.metrics["refit"])["nrmse"],
            "nrmse_after": result.metrics.get("extended", result.metrics["refit"])["nrmse"],
            "gain": result.gain,
            "extended": result.extended.readable() if result.extended else None,
            "wall_time_s": time.perf_counter() - start,
        }
        print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
