"""The limits of the data: the TRUE PSAT 5.1 structure fitted on the benchmark's own data.

What the search could at best achieve if it wrote exactly the right equations: the true
structure (one free coefficient per true term) is fitted with the project's own fitter
(``jaxdmd.fit.fit_batch`` through ``jaxdmd.search``; matched fitting of the estimated
derivatives, as ``python -m jaxdmd.run`` does) on the same training data as the run (the paper's
protocol, generator 31, bus-15 fault, 1 % noise of range on the training states), and reports

- DE: every coefficient against the truth (relative error) and the training NMSE, fitted to the
  estimated derivatives (unweighted and weighted) and in the integral form (0.5 s windows);
- AE: the stator equations solved for i_d, i_q, and P_e (= e'_q i_q + e''_d i_d written in the
  states and the terminal phasor), v_d, v_q: R^2 on the bus-28 test data as the run reports it
  (the protocol's test data are noise-free), and R^2 on the same test data with the training
  noise added to the test states (what a noisy test recording would show); and fitted by
  bias-compensated least squares as the AE loop's final refit fits (errors in variables
  corrected with noise variances estimated from the data), on the smoothed states and on the
  states estimated with the DE fit above (integral form) as process model, then by maximum
  likelihood with the states unknown (``jaxdmd.refine.refit_joint``, as ``--ae-joint``).

Ground truth lives here (benchmarks/), never in jaxdmd/.

Run:  python benchmarks/oracle.py [--operating-points 4] [--noise 0.01] [--seed 0] [--json F]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

# bus-31 machine of the IEEE 39-bus benchmark (docs/benchmark-system.md), 100 MVA base
M, XD, XDP, XQ, XQP = 60.6, 0.295, 0.0697, 0.282, 0.170
TD0, TQ0, TQ02, RA = 6.56, 1.5, 0.04, 0.0027
OMEGA_B = 2 * np.pi * 60
GAMMA_Q = (XDP / XQP) * (TQ02 / TQ0) * (XQ - XQP)
K = 1.0 / (RA**2 + XDP**2)

# the true state equations, one coefficient per term: (term, true coefficient)
TRUE_DE = {
    "delta": [("omega", OMEGA_B), ("1", -OMEGA_B)],
    "omega": [("P_m", 1 / M), ("P_e", -1 / M)],
    "e_qp": [("e_qp", -1 / TD0), ("i_d", -(XD - XDP) / TD0), ("v_f", 1 / TD0)],
    "e_dp": [("e_dp", -1 / TQ0), ("i_q", (XQ - XQP - GAMMA_Q) / TQ0)],
    "e_dpp": [
        ("e_dpp", -1 / TQ02),
        ("e_dp", 1 / TQ02),
        ("i_q", (XQP - XDP + GAMMA_Q) / TQ02),
    ],
}
VD = "V * jnp.sin(delta - theta)"
VQ = "V * jnp.cos(delta - theta)"
# the stator equations solved for the currents, and P_e = e'_q i_q + e''_d i_d expanded
TRUE_AE = {
    "i_d": [("e_dpp", K * RA), (VD, -K * RA), ("e_qp", K * XDP), (VQ, -K * XDP)],
    "i_q": [("e_qp", K * RA), (VQ, -K * RA), ("e_dpp", -K * XDP), (VD, K * XDP)],
    "P_e": [
        ("e_qp * e_qp", K * RA),
        ("e_dpp * e_dpp", K * RA),
        (f"e_qp * {VQ}", -K * RA),
        (f"e_dpp * {VD}", -K * RA),
        (f"e_qp * {VD}", K * XDP),
        (f"e_dpp * {VQ}", -K * XDP),
    ],
    "v_d": [(VD, 1.0)],
    "v_q": [(VQ, 1.0)],
}


def _source(name: str, args: list[str], outputs: list[str], eqs: list[list[str]]) -> str:
    body, k = [], 0
    for out, terms in zip(outputs, eqs, strict=True):
        parts = []
        for t in terms:
            parts.append(f"p[{k}]" if t == "1" else f"p[{k}] * {t}")
            k += 1
        body.append(f"    {out} = " + " + ".join(parts))
    head = f"def {name}({', '.join([*args, 'p'])}):"
    return "\n".join([head, *body, f"    return {', '.join(outputs)}"]) + "\n"


def _fit(source: str, problem, args: list[str], n_out: int, seed: int):
    import jax

    from jaxdmd.search import fit_problem
    from jaxdmd.skeleton import compile_skeleton

    sk = compile_skeleton(source, variables=tuple(args), n_outputs=n_out)
    (res,) = fit_problem([sk], problem, jax.random.key(seed))
    if res.error is not None:
        raise RuntimeError(res.error)
    return sk, res


def _noisy(datasets, noise: float, seed: int):
    """The datasets with the training noise (sigma = noise x range) added to the states."""
    import jax

    from jaxdmd.data import Dataset

    out = []
    for i, ds in enumerate(datasets):
        ch = {n: np.asarray(ds[n], dtype=float).copy() for n in ds.names}
        z = np.asarray(
            jax.random.normal(jax.random.key(10_000 + seed * 100 + i), (ds.n_samples, 5))
        )
        for j, s in enumerate(ds.state_names):
            ch[s] = ch[s] + noise * np.ptp(ch[s]) * z[:, j]
        roles = {n: ds.role(n) for n in ds.names}
        out.append(Dataset.create(ds.t, ch, roles, events=ds.events, label=ds.label + " noisy"))
    return out


def _bias_compensated_ae(
    train, test, source: str, targets: list[str], estimates=None, de=None
) -> dict:
    """The true AE structure fitted as the AE loop's final refit fits its equations:
    ``jaxdmd.refine.refit_bias_compensated`` (bias-compensated least squares on estimated
    states: ``estimates``, else the smoothed states, their noise estimated from the data); with
    ``de`` (state equations) then ``jaxdmd.refine.refit_joint`` (maximum likelihood with the
    states unknown). No truth is used but the structure."""
    from jaxdmd.prompts import Contract, Variable
    from jaxdmd.refine import refit_bias_compensated, refit_joint, smoothed_states
    from jaxdmd.rollout import algebraic_r2
    from jaxdmd.search import Equations

    states = train[0].state_names
    contract = Contract(
        loop="AE",
        targets=tuple(targets),
        states=tuple(Variable(s, "state") for s in states),
        library=(Variable("V", "boundary"), Variable("theta", "boundary")),
        function_name="algebraic",
    )
    true = np.array([c for y in targets for _, c in TRUE_AE[y]])
    start = Equations(contract, source, tuple(np.zeros(true.size)), (), float("nan"))
    if estimates is None:
        estimates = smoothed_states(train, states)
    refit, report = refit_bias_compensated(start, estimates)
    if de is not None:
        refit, report = refit_joint(de, refit, train, estimates)
    errors, k = {}, 0
    for y in targets:
        n = len(TRUE_AE[y])
        errors[y] = [float(e) for e in np.asarray(refit.params[k : k + n]) / true[k : k + n] - 1]
        k += n
    return {"equations": errors, "test_r2": algebraic_r2(refit, test), "report": report}


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--operating-points", type=int, default=4)
    parser.add_argument("--noise", type=float, default=0.01)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--generator", type=int, default=31)
    parser.add_argument("--json", help="also write the figures to this file")
    args = parser.parse_args(argv)
    if args.generator != 31:
        raise SystemExit("the ground truth here is the bus-31 machine")

    import jax.numpy as jnp

    from jaxdmd.data import stack_samples
    from jaxdmd.grid import benchmark_protocol
    from jaxdmd.problems import de_problem
    from jaxdmd.rollout import r2

    t0 = time.perf_counter()
    data = benchmark_protocol((31,), args.operating_points, args.noise, args.seed)
    train, test = list(data.train[31]), list(data.test[31])
    out: dict = {"settings": vars(args)}

    # ---- DE: the true structure, matched fit on the noisy training data (as the run fits),
    # unweighted (the run's default), weighted by the inverse noise of the estimates (--weighted),
    # and in the integral form over 0.5 s windows of the smoothed states (--integral 0.5)
    states = list(train[0].state_names)
    de_args = [*states, "i_d", "i_q", "P_e", "P_m", "v_f"]
    eqs = [[t for t, _ in TRUE_DE[s]] for s in states]
    outputs = [f"d_{s}" for s in states]  # not the states' names: a line must not shadow them
    source = _source("equation", de_args, outputs, eqs)
    out["de"] = {}
    for mode in ("unweighted", "weighted", "integral"):
        if mode == "integral":
            problem, _ = de_problem(train, integral=0.5, smooth=True)
        else:
            problem, _ = de_problem(train, matched=True, weighted=mode == "weighted")
        sk, res = _fit(source, problem, de_args, len(states), 0)
        if mode == "integral":
            de_integral = (sk, [float(x) for x in res.params])
        de_rows, k = {}, 0
        for s in states:
            rows = []
            for term, true in TRUE_DE[s]:
                got = float(res.params[k])
                rows.append({"term": term, "true": true, "fit": got, "rel_err": got / true - 1})
                k += 1
            de_rows[s] = {"nmse": float(res.losses[states.index(s)]), "coefficients": rows}
        out["de"][mode] = {
            "equations": de_rows,
            "max_rel_err": max(
                abs(r["rel_err"]) for v in de_rows.values() for r in v["coefficients"]
            ),
        }

    # ---- AE: the true structure on the training data (noisy states, clean algebraic channels);
    # "raw": the noisy states as regressors; "smoothed": the states smoothed by the derivative
    # estimator (Dataset.with_estimated_derivatives(smooth=True)) as regressors
    from jaxdmd.search import Problem

    targets = list(TRUE_AE)
    ae_args = [*states, "V", "theta"]
    eqs = [[t for t, _ in TRUE_AE[y]] for y in targets]
    source = _source("algebraic", ae_args, [f"{y}_" for y in targets], eqs)
    true_p = np.array([c for y in targets for _, c in TRUE_AE[y]])
    noisy_test = _noisy(test, args.noise, args.seed)
    out["ae"] = {}
    for mode in ("raw", "smoothed"):
        data = (
            train if mode == "raw" else [ds.with_estimated_derivatives(smooth=True) for ds in train]
        )
        variables = {k: jnp.asarray(v) for k, v in stack_samples(data, data[0].names).items()}
        ae_problem = Problem(
            variables=variables,
            targets=jnp.stack([variables[t] for t in targets]),
            target_names=tuple(targets),
            catalog=(),
        )
        sk, res = _fit(source, ae_problem, ae_args, len(targets), 1)

        def r2_on(datasets, params, sk=sk):
            d = stack_samples(datasets, datasets[0].names)
            pred = np.asarray(sk({k: jnp.asarray(v) for k, v in d.items()}, jnp.asarray(params)))
            return {y: r2(pred[j], d[y]) for j, y in enumerate(targets)}

        rows, k = {}, 0
        for j, y in enumerate(targets):
            coefs = []
            for term, true in TRUE_AE[y]:
                got = float(res.params[k])
                coefs.append({"term": term, "true": true, "fit": got, "rel_err": got / true - 1})
                k += 1
            rows[y] = {"train_nmse": float(res.losses[j]), "coefficients": coefs}
        out["ae"][mode] = {
            "equations": rows,
            "test_r2": r2_on(test, res.params),
            "noisy_test_r2": r2_on(noisy_test, res.params),
        }
        if mode == "raw":
            out["ae_true_params"] = {
                "test_r2": r2_on(test, true_p),
                "noisy_test_r2": r2_on(noisy_test, true_p),
            }
    out["ae_bias_compensated"] = _bias_compensated_ae(train, test, source, targets)
    # the states estimated by the Kalman smoother whose process model is the DE fitted above in
    # the integral form (as python -m jaxdmd.run --ae-states model does with the discovered DE)
    from jaxdmd.estimate import model_smoother
    from jaxdmd.refine import smoothed_states

    noise = [e.noise for e in smoothed_states(train, states)]
    estimates = model_smoother(*de_integral, states, train, noise)
    out["ae_model_states"] = _bias_compensated_ae(train, test, source, targets, estimates)
    # ... and then refitted by maximum likelihood with the states unknown (--ae-joint)
    from jaxdmd.prompts import Contract, Variable
    from jaxdmd.search import Equations

    channels = [Variable(n, train[0].role(n)) for n in de_args if n not in states]
    de_contract = Contract(
        loop="DE",
        targets=tuple(states),
        states=tuple(Variable(s, "state") for s in states),
        library=tuple(channels),
        function_name="equation",
    )
    de = Equations(de_contract, de_integral[0].source, tuple(de_integral[1]), (), float("nan"))
    out["ae_joint"] = _bias_compensated_ae(train, test, source, targets, estimates, de)
    out["wall_time_s"] = time.perf_counter() - t0

    print(f"Oracle: {args.operating_points} training points, noise {args.noise}, seed {args.seed}")
    for mode, d in out["de"].items():
        print(f"  DE, {mode}:")
        for s, v in d["equations"].items():
            cs = ", ".join(
                f"{r['term']} {r['fit']:.5g} (true {r['true']:.5g}, {100 * r['rel_err']:+.2f} %)"
                for r in v["coefficients"]
            )
            print(f"    d{s}/dt  NMSE {v['nmse']:.4f}: {cs}")
        print(f"    max |coefficient error| {100 * d['max_rel_err']:.2f} %")
    for mode, v in out["ae"].items():
        print(f"  AE, {mode} training states as regressors:")
        for y, e in v["equations"].items():
            errs = ", ".join(f"{100 * r['rel_err']:+.1f} %" for r in e["coefficients"])
            print(
                f"    {y}: train NMSE {e['train_nmse']:.4f}; coefficients {errs}; test R^2 "
                f"{v['test_r2'][y]:.5f} (clean test data), {v['noisy_test_r2'][y]:.4f} (noisy)"
            )
    bc = out["ae_bias_compensated"]
    print(
        "  AE, bias-compensated least squares (smoothed states, noise estimated): test R^2 "
        + ", ".join(f"{y} {v:.5f}" for y, v in bc["test_r2"].items())
    )
    ms = out["ae_model_states"]
    print(
        "  AE, the same on the states estimated with the DE model (Kalman smoother): test R^2 "
        + ", ".join(f"{y} {v:.5f}" for y, v in ms["test_r2"].items())
    )
    jt = out["ae_joint"]
    print(
        "  AE, then maximum likelihood with the states unknown (--ae-joint, "
        f"{jt['report'].get('steps')} BFGS steps): test R^2 "
        + ", ".join(f"{y} {v:.6f}" for y, v in jt["test_r2"].items())
    )
    t = out["ae_true_params"]
    print(
        "  AE, true parameters: test R^2 "
        + ", ".join(f"{y} {t['test_r2'][y]:.6f}" for y in targets)
        + "; with noisy test states "
        + ", ".join(f"{y} {t['noisy_test_r2'][y]:.4f}" for y in targets)
    )
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1))
    return out


if __name__ == "__main__":
    main()
