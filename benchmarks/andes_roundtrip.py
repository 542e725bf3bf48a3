"""A discovered model against ANDES's simulation of the standard record exported from it.

``jaxdmd.export`` reads a discovered PSAT 5.1-type model off as its standard record (H, x_d,
x'_d, T'_d0, ...: GENROU with x''_d = x''_q = x'_d, exact for PSAT 5.1). This script writes that
record as an ANDES case (the machine on a bus behind a line to an infinite bus, a fault of
0.15 s, as ``tests/test_export.py`` does for a known machine), simulates it in ANDES, and rolls
the *discovered* model itself (``jaxdmd.load``, its own untied coefficients) out closed on
ANDES's terminal voltage, angle and inputs. Each model starts from its own equilibrium at the
same operating point: the discovered model's 1/T'_d0 seen from v_f and from e'_q differ a
little, and so do its P_e line and ANDES's air-gap torque, so v_f and P_m are played in shifted
by the constants that make its d e'_q/dt and d omega/dt vanish at the first sample. Printed: R^2 of
delta - delta(0), omega, e'_q, e''_d (GENROU's psi''_q) and P_e (GENROU's air-gap torque).

    python benchmarks/andes_roundtrip.py runs/demo

Needs ANDES (the ``export`` or ``test`` extra). The ANDES helpers are the tests' own.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

FAULT = (1.0, 1.15)
STATES = ("delta", "omega", "e_qp", "e_dp", "e_dpp")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("run", help="a discovery's output folder (model.py) or model file")
    parser.add_argument("--p0", type=float, default=5.0, help="the machine's power, pu (5.0)")
    args = parser.parse_args(argv)

    from test_export import andes_run, as_recording, r2

    import jaxdmd
    from jaxdmd.data import Dataset
    from jaxdmd.export import andes_case, standard_machine

    model = jaxdmd.load(args.run)
    machine = standard_machine(model)
    p = machine.params
    print("record:", {k: round(v, 6) for k, v in p.items()})
    with tempfile.TemporaryDirectory() as tmp:
        case = Path(tmp) / "genrou.json"
        case.write_text(
            json.dumps(andes_case(machine, p0=args.p0, v0=1.0, x_line=0.05, fault=FAULT))
        )
        ss = andes_run(case)
    ts, g = ss.dae.ts, ss.GENROU

    def x(v):
        return np.asarray(ts.x[:, v.a[0]])

    def y(v):
        return np.asarray(ts.y[:, v.a[0]])

    # e'_d is no GENROU state: PSAT's e'_d starts where its equation vanishes
    gamma_q = (p["x'_d"] / p["x'_q"]) * (p["T''_q0"] / p["T'_q0"]) * (p["x_q"] - p["x'_q"])
    e_dp0 = (p["x_q"] - p["x'_q"] - gamma_q) * float(y(g.Iq)[0])
    channels = {
        "delta": x(g.delta), "omega": x(g.omega), "e_qp": x(g.e1q),
        "e_dp": np.full_like(x(g.e1q), e_dp0), "e_dpp": y(g.psi2q), "P_m": y(g.tm),
        "v_f": y(g.vf), "P_e": y(g.te), "V": y(g.v), "theta": y(g.a),
    }  # fmt: skip
    roles = {s: "state" for s in STATES} | {"P_m": "input", "v_f": "input", "P_e": "algebraic"}
    roles |= {"V": "boundary", "theta": "boundary"}
    rec = as_recording(ss, channels, roles, events=FAULT)
    ch = {n: np.asarray(rec[n]).copy() for n in rec.names}
    dt = float(rec.t[1] - rec.t[0])
    driven = (("v_f", "e_qp"), ("P_m", "omega"))  # each input and the state it drives

    def rollout(channels: dict[str, np.ndarray]):
        return model.simulate(Dataset.create(rec.t, channels, roles, events=FAULT))

    # the coefficients of v_f in d e'_q/dt and of P_m in d omega/dt, by their effect: one unit
    # more of each played in, the initial rate of the state it drives
    base = rollout(ch)
    gains = {
        name: (float(rollout(dict(ch, **{name: ch[name] + 1e-3}))[state][1])
               - float(base[state][1])) / dt / 1e-3
        for name, state in driven
    }  # fmt: skip
    sim = base
    for _ in range(3):  # Newton steps on the two initial rates
        for name, state in driven:
            rate = (float(sim[state][1]) - float(sim[state][0])) / dt
            ch[name] = ch[name] - rate / gains[name]
        sim = rollout(ch)
    rec = Dataset.create(rec.t, ch, roles, events=FAULT)
    if sim.diverged:
        print("the discovered model diverges on ANDES's fault")
        return 1
    got = {s: np.asarray(sim[s]) for s in ("delta", "omega", "e_qp", "e_dpp")}
    got["P_e"] = np.asarray(sim.algebraic["P_e"])
    want = {s: np.asarray(rec[s]) for s in got}
    for d in (got, want):
        d["delta"] = d["delta"] - d["delta"][0]
    print(f"delta swings {np.ptp(want['delta']):.3f} rad")
    print("R^2, ANDES's run of the record against the discovered model's rollout:")
    for s in got:
        print(f"  {s:6s} {r2(want[s], got[s]):.6f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
