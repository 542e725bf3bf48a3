"""Benchmark of jaxdmd.fit: a round of 16 candidates x 8 restarts, 1000 samples, 5 equations.

Compares, wall time INCLUDING compilation, each part in a fresh process:

  (a) ``jaxdmd.fit.fit_batch`` on the whole round, as the search calls it: exact least squares
      for what is affine in p, Levenberg-Marquardt for the rest on the lowered programs, run on
      the host in NumPy (``FitConfig(backend="host")``, the default: nothing is compiled).
      Reported two ways:
      ``a_seconds``             a cold process (the first round of a search),
      ``a_next_round_seconds``  a second round in the same process with the candidates renamed
                                (new sources: nothing candidate-specific is cached).
  (a') the same with the LM loop in the jitted register-machine interpreter
      (``FitConfig(backend="xla")``): ``a_xla_seconds`` cold (tracing and compiling the
      interpreter fit, once per process), ``a_xla_next_round_seconds`` the second round.
  (b) the same candidates jitted and fitted one at a time: ``fit_batch`` per candidate with
      ``FitConfig(interpreter=False)`` (one XLA compile per nonlinear candidate, the same LM and
      exact least squares for the affine ones); a cold process, as new candidates always are,
  (c) LLM-SR's way: scipy BFGS per candidate from parameters at 1.0, NumPy objective (the summed
      per-equation NMSE), finite-difference gradients.

The data are synthetic: 5th-order synchronous-machine equations (PSAT 5.1, IEEE 39-bus machine at
bus 31) evaluated on two smooth random recordings of 500 samples each; the targets (state
derivatives) carry Gaussian noise of 1 % of their range. The candidates are skeletons like the
ones a model writes for this machine: 4 to 15 parameters, some nonlinear in p.

Run:  python benchmarks/fit_speed.py            (prints one JSON line)
      python benchmarks/fit_speed.py --part a --restarts 4   (one part, other settings)
      python benchmarks/fit_speed.py --samples 16000 --skip b  (longer data)
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from collections.abc import Callable

import numpy as np

sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parents[1]))

VARIABLES = ("delta", "omega", "eq1", "ed1", "ed2", "id", "iq", "Pe", "V", "theta", "Pm", "vf")

# the true machine (bus 31 of the IEEE 39-bus system, 100 MVA base); D and T''_q0 are choices
TRUE = dict(
    Wb=2 * np.pi * 60, M=60.6, D=2.0, xd=0.295, xd1=0.0697, xq=0.282, xq1=0.170,
    Td0=6.56, Tq0=1.5, Tq02=0.04, ra=0.0027,
)  # fmt: skip


def make_data(n: int = 1000, seed: int = 0) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Two recordings of n/2 samples, concatenated; targets = noisy true derivatives [5, n]."""
    rng = np.random.default_rng(seed)
    c = TRUE
    gq = (c["xd1"] / c["xq1"]) * (c["Tq02"] / c["Tq0"]) * (c["xq"] - c["xq1"])
    parts = []
    for _ in range(2):
        t = np.linspace(0.0, 5.0, n // 2)

        def wave(amp, rate=0.5, freq=(0.5, 2.0), t=t):
            f = rng.uniform(*freq)
            return amp * np.exp(-rate * t) * np.sin(2 * np.pi * f * t + rng.uniform(0, 6.3))

        v = {
            "delta": 0.8 + wave(0.3),
            "omega": 1.0 + wave(2e-3),
            "eq1": 1.0 + wave(0.05),
            "ed1": 0.2 + wave(0.05),
            "ed2": 0.25 + wave(0.05),
            "V": 1.0 + wave(0.1, rate=1.0),
            "theta": 0.1 + wave(0.2),
            "Pm": 6.5 + 0.0 * t,
            "vf": 2.0 + wave(0.1, rate=0.2),
        }
        vd = v["V"] * np.sin(v["delta"] - v["theta"])
        vq = v["V"] * np.cos(v["delta"] - v["theta"])
        k = 1.0 / (c["ra"] ** 2 + c["xd1"] ** 2)
        v["id"] = k * (c["ra"] * (v["ed2"] - vd) + c["xd1"] * (v["eq1"] - vq))
        v["iq"] = k * (c["ra"] * (v["eq1"] - vq) - c["xd1"] * (v["ed2"] - vd))
        v["Pe"] = v["eq1"] * v["iq"] + v["ed2"] * v["id"]
        parts.append(v)
    data = {name: np.concatenate([p[name] for p in parts]) for name in VARIABLES}
    d = data
    xdot = np.stack(
        [
            c["Wb"] * (d["omega"] - 1),
            (d["Pm"] - d["Pe"] - c["D"] * (d["omega"] - 1)) / c["M"],
            (-d["eq1"] - (c["xd"] - c["xd1"]) * d["id"] + d["vf"]) / c["Td0"],
            (-d["ed1"] + (c["xq"] - c["xq1"] - gq) * d["iq"]) / c["Tq0"],
            (-d["ed2"] + d["ed1"] + (c["xq1"] - c["xd1"] + gq) * d["iq"]) / c["Tq02"],
        ]
    )
    noise = 0.01 * (xdot.max(axis=1) - xdot.min(axis=1))[:, None]
    return data, xdot + noise * rng.standard_normal(xdot.shape)


# 16 candidate skeletons of different structure, in the style of LLM-SR (np namespace)
CANDIDATES: list[tuple[str, int]] = [
    (
        """def equation(delta, omega, eq1, ed1, ed2, id, iq, Pe, Pm, vf, p):
    return (p[0] * (omega - 1), p[1] * Pm + p[2] * Pe + p[3] * (omega - 1),
            p[4] * eq1 + p[5] * id + p[6] * vf, p[7] * ed1 + p[8] * iq,
            p[9] * ed2 + p[10] * ed1 + p[11] * iq)""",
        12,
    ),
    (
        """def equation(delta, omega, eq1, ed1, ed2, iq, Pe, Pm, vf, p):
    return (p[0] * omega + p[1], p[2] * (Pm - Pe), p[3] * (vf - eq1), p[4] * ed1,
            p[5] * (ed1 - ed2) + p[6] * iq)""",
        7,
    ),
    (
        """def equation(delta, omega, eq1, ed1, ed2, id, iq, V, theta, Pm, vf, p):
    pe = p[1] * V * np.sin(delta - theta - p[2])
    return (p[0] * (omega - 1), p[3] * (Pm - pe) + p[4] * (omega - 1),
            (vf - eq1 - p[5] * id) / p[6], (p[7] * iq - ed1) / p[8],
            (ed1 - ed2 + p[9] * iq) / p[10])""",
        11,
    ),
    (
        """def equation(omega, eq1, ed1, ed2, id, iq, Pe, Pm, vf, p):
    return (p[0] * (omega - 1), (Pm - Pe - p[1] * (omega - 1)) / p[2],
            (vf - eq1 - p[3] * id) / p[4], (p[5] * iq - ed1) / p[6],
            (ed1 - ed2 + p[7] * iq) / p[8])""",
        9,
    ),
    (
        """def equation(delta, omega, eq1, ed1, ed2, id, iq, Pe, Pm, vf, p):
    return (p[0] * (omega - p[1]), p[2] * Pm + p[3] * Pe + p[4] * omega + p[5],
            p[6] * eq1 + p[7] * id + p[8] * vf + p[9], p[10] * ed1 + p[11] * iq,
            p[12] * ed2 + p[13] * ed1 + p[14] * iq)""",
        15,
    ),
    (
        """def equation(delta, omega, eq1, ed1, ed2, iq, Pe, Pm, p):
    return (p[0] * np.tanh(p[1] * (omega - 1)), p[2] * (Pm - Pe), p[3], p[4] * ed1 + p[5] * iq,
            p[6] * (ed1 - ed2))""",
        7,
    ),
    (
        """def equation(delta, omega, eq1, ed1, ed2, id, iq, V, theta, Pm, vf, p):
    vd = V * np.sin(delta - theta)
    vq = V * np.cos(delta - theta)
    return (p[0] * (omega - 1), p[1] * Pm + p[2] * (vd * id + vq * iq) + p[3] * (omega - 1),
            p[4] * eq1 + p[5] * id + p[6] * vf, p[7] * ed1 + p[8] * iq + p[9] * vd,
            p[10] * ed2 + p[11] * ed1 + p[12] * iq)""",
        13,
    ),
    (
        """def equation(omega, eq1, ed1, ed2, id, iq, Pe, Pm, vf, p):
    return (p[0] * (omega - 1), p[1] * (Pm - Pe), p[2] * eq1 * np.exp(-p[3] * eq1) + p[4] * vf,
            -ed1 / p[5], (ed1 - ed2) / p[6] + p[7] * iq)""",
        8,
    ),
    (
        """def equation(delta, omega, eq1, ed1, ed2, id, iq, Pe, Pm, vf, p):
    return (p[0] * (omega - 1) + p[1] * (omega - 1) ** 2, p[2] * Pm + p[3] * Pe,
            p[4] * eq1 + p[5] * eq1 ** 2 + p[6] * id + p[7] * vf, p[8] * ed1 + p[9] * iq,
            p[10] * ed2 + p[11] * ed1 + p[12] * iq)""",
        13,
    ),
    (
        """def equation(delta, omega, eq1, ed1, ed2, id, iq, Pe, Pm, vf, p):
    return (p[0] * np.sin(omega - 1), p[1] * Pm + p[2] * Pe, p[3] * (vf - eq1),
            p[4] * ed1 + p[5] * iq, p[6] * ed2 + p[7] * iq)""",
        8,
    ),
    (
        """def equation(delta, omega, eq1, ed1, ed2, id, iq, V, theta, Pm, vf, p):
    return (p[0] * (omega - 1), p[1] * Pm + p[2] * V * np.sin(delta - theta) * id
            + p[3] * V * np.cos(delta - theta) * iq, p[4] * eq1 + p[5] * id + p[6] * vf,
            p[7] * ed1 + p[8] * iq, p[9] * ed2 + p[10] * ed1 + p[11] * iq)""",
        12,
    ),
    (
        """def equation(omega, eq1, ed1, ed2, id, iq, Pe, Pm, vf, p):
    return (p[0] * (omega - 1), (Pm - Pe) / p[1], (vf - eq1) / p[2] - p[3] * id,
            p[4] * ed1 + p[5] * iq, p[6] * ed2 + p[7] * ed1 + p[8] * iq)""",
        9,
    ),
    (
        """def equation(delta, omega, eq1, ed1, ed2, id, iq, Pe, Pm, vf, p):
    return (p[0] * (omega - 1), p[1] * Pm + p[2] * Pe + p[3] * np.sin(delta),
            p[4] * eq1 + p[5] * id + p[6] * vf, p[7] * ed1 + p[8] * iq,
            p[9] * ed2 + p[10] * ed1 + p[11] * iq + p[12] * np.cos(delta))""",
        13,
    ),
    (
        """def equation(omega, eq1, ed1, ed2, iq, Pe, Pm, vf, p):
    return (p[0] * (omega - 1), p[1] * (Pm - Pe), p[2] * (vf - eq1), p[3] * (iq - ed1),
            p[3] * (ed1 - ed2))""",
        4,
    ),
    (
        """def equation(delta, omega, eq1, ed1, ed2, id, iq, V, theta, Pm, vf, p):
    return (p[0] * (omega - 1), p[1] * Pm + p[2] * V * eq1 * np.sin(delta - theta + p[3])
            + p[4] * (omega - 1), p[5] * eq1 + p[6] * id + p[7] * vf,
            p[8] * ed1 + p[9] * iq, p[10] * ed2 + p[11] * ed1 + p[12] * iq)""",
        13,
    ),
    (
        """def equation(omega, eq1, ed1, ed2, id, iq, Pe, Pm, vf, p):
    return (p[0] * (omega - 1), p[1] * (Pm - Pe) / (1 + p[2] * (omega - 1)),
            p[3] * (vf - eq1 - p[4] * id), p[5] * (iq * p[6] - ed1),
            p[7] * (ed1 - ed2 + p[8] * iq))""",
        9,
    ),
]


def _arguments(source: str) -> tuple[str, ...]:
    head = source.split("(", 1)[1].split(")", 1)[0]
    return tuple(a.strip() for a in head.split(",") if a.strip() != "p")


def _function(source: str, np_module) -> Callable:
    scope: dict = {"np": np_module}
    exec(source, scope)
    return scope["equation"]


def skeletons(name: str = "equation") -> list:
    """The candidates as checked and compiled skeletons (``name``: the functions' name)."""
    from jaxdmd.skeleton import compile_skeleton

    out = []
    for src, n_params in CANDIDATES:
        src = src.replace("def equation(", f"def {name}(")
        sk = compile_skeleton(src, variables=VARIABLES, n_outputs=5)
        assert sk.n_params == n_params, (sk.n_params, n_params)
        out.append(sk)
    return out


def part_jax(
    one_at_a_time: bool, backend: str, polish_steps: int, restarts: int, samples: int
) -> dict:
    import jax

    # imports stay outside every part's timer (part c imports scipy.optimize before its own)
    import scipy.linalg
    import scipy.sparse  # noqa: F401

    import jaxdmd  # noqa: F401  (float64)
    from jaxdmd.fit import FitConfig, fit_batch

    data, targets = make_data(samples)
    cands = skeletons()
    config = FitConfig(
        restarts=restarts, polish_steps=polish_steps, interpreter=not one_at_a_time,
        backend=backend,
    )  # fmt: skip
    key = jax.random.key(0)
    t0 = time.perf_counter()
    if one_at_a_time:
        results = [r for s in cands for r in fit_batch([s], data, targets, key=key, config=config)]
    else:
        results = fit_batch(cands, data, targets, key=key, config=config)
    seconds = time.perf_counter() - t0
    losses = [float(np.mean(r.losses)) for r in results]
    out = {"seconds": seconds, "losses": losses, "errors": [r.error for r in results]}
    if not one_at_a_time:  # the next round of a search: new candidate sources, same process
        renamed = skeletons(name="candidate")
        t0 = time.perf_counter()
        again = fit_batch(renamed, data, targets, key=jax.random.key(1), config=config)
        out["next_round_seconds"] = time.perf_counter() - t0
        out["next_round_losses"] = [float(np.mean(r.losses)) for r in again]
    return out


def part_scipy(samples: int) -> dict:
    from scipy.optimize import minimize

    from jaxdmd.fit import nmse

    data, targets = make_data(samples)
    t0 = time.perf_counter()
    losses = []
    for src, n_params in CANDIDATES:
        f = _function(src, np)
        args = [data[a] for a in _arguments(src)]

        def loss(p, f=f, args=args):
            with np.errstate(all="ignore"):
                pred = np.stack([np.broadcast_to(o, targets.shape[1]) for o in f(*args, p)])
                val = float(np.sum(nmse(pred, targets)))
            return val if np.isfinite(val) else 1e300

        res = minimize(loss, np.ones(n_params), method="BFGS")
        losses.append(loss(res.x) / targets.shape[0])
    return {"seconds": time.perf_counter() - t0, "losses": losses}


def _run_part(argv: list[str]) -> dict:
    out = subprocess.run(
        [sys.executable, __file__, *argv], capture_output=True, text=True, check=True
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--part", choices=["a", "x", "b", "c"], help="run one part in this process")
    ap.add_argument("--polish-steps", type=int, default=50)
    ap.add_argument("--restarts", type=int, default=8)
    ap.add_argument("--samples", type=int, default=1000, help="samples (two recordings)")
    ap.add_argument("--skip", default="", help="parts to skip, e.g. 'xb'")
    ns = ap.parse_args()
    common = ["--polish-steps", str(ns.polish_steps), "--restarts", str(ns.restarts)]
    common += ["--samples", str(ns.samples)]
    if ns.part in ("a", "x", "b"):
        backend = "xla" if ns.part == "x" else "host"
        args = (ns.part == "b", backend, ns.polish_steps, ns.restarts, ns.samples)
        print(json.dumps(part_jax(*args)))
        return
    if ns.part == "c":
        print(json.dumps(part_scipy(ns.samples)))
        return
    report: dict = {
        "candidates": len(CANDIDATES), "restarts": ns.restarts, "samples": ns.samples,
        "equations": 5, "polish_steps": ns.polish_steps,
        "load_average": [round(x, 2) for x in os.getloadavg()],
    }  # fmt: skip
    parts = {p: _run_part(["--part", p, *common]) for p in "axbc" if p not in ns.skip}
    names = {"a": "a", "x": "a_xla", "b": "b", "c": "c"}
    for p, r in parts.items():
        report[f"{names[p]}_seconds"] = round(r["seconds"], 3)
        if "next_round_seconds" in r:
            report[f"{names[p]}_next_round_seconds"] = round(r["next_round_seconds"], 3)
        report[f"{names[p]}_mean_nmse"] = float(np.mean(r["losses"]))
        report[f"{names[p]}_median_nmse"] = float(np.median(r["losses"]))
    if "a" in parts:
        a = parts["a"]
        report["a_dropped"] = sum(e is not None for e in a["errors"])
        report["a_next_round_mean_nmse"] = float(np.mean(a["next_round_losses"]))
        for p in "xbc":
            if p in parts:
                report[f"{names[p]}_over_a"] = round(parts[p]["seconds"] / a["seconds"], 2)
                report[f"{names[p]}_over_a_next_round"] = round(
                    parts[p]["seconds"] / a["next_round_seconds"], 2
                )
                la, lp = np.array(a["losses"]), np.array(parts[p]["losses"])
                report[f"a_loss_le_{names[p]}"] = int(np.sum(la <= lp * (1 + 1e-6) + 1e-12))
    report["load_average_end"] = [round(x, 2) for x in os.getloadavg()]
    print(json.dumps(report))


if __name__ == "__main__":
    main()
