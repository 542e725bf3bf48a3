"""Tests of benchmarks/table1.py: aggregation, goal check, the docs section, the oracle skeleton."""

from __future__ import annotations

import importlib.util
import math
import sys
from pathlib import Path

import numpy as np
import pytest

import jaxdmd  # noqa: F401  (float64)

_PATH = Path(__file__).resolve().parents[1] / "benchmarks" / "table1.py"
_spec = importlib.util.spec_from_file_location("table1", _PATH)
assert _spec is not None and _spec.loader is not None
table1 = importlib.util.module_from_spec(_spec)
sys.modules["table1"] = table1
_spec.loader.exec_module(table1)


def _score(mape: float, r2: float, diverged: bool = False) -> dict:
    per = {s: {"mape": mape, "r2": r2, "nrmse": 0.1, "nmae": 0.05} for s in table1.STATES}
    if diverged:
        per["omega"] = {"mape": math.inf, "r2": -math.inf, "nrmse": math.inf, "nmae": math.inf}
    mean = {k: float(np.mean([p[k] for p in per.values()])) for k in table1.METRIC_KEYS}
    full = {"per_state": per, "mean": mean}
    return {
        "full": full,
        "fault": full,
        "diverged": diverged,
        "diverged_at": 2.0 if diverged else None,
    }


def _generator(gen: int, values: dict[str, tuple[float, float]], diverged=()) -> dict:
    rows = {}
    for key in table1.ROWS:
        if key in values:
            m, r = values[key]
            rows[key] = table1.summarise_recordings(
                [_score(m, r), _score(m, r, diverged=key in diverged)]
            )
            rows[key].update(rounds=10 if key.startswith("jaxdmd") else None, wall_time_s=5.0)
        else:
            rows[key] = {"error": "RuntimeError: boom"}
    return {"generator": gen, "status": "done", "rows": rows}


def test_summarise_and_aggregate() -> None:
    row = table1.summarise_recordings([_score(1.0, 0.9), _score(3.0, 0.5)])
    assert row["mape"] == pytest.approx(2.0) and row["r2"] == pytest.approx(0.7)
    assert row["n_diverged"] == 0 and row["n_recordings"] == 2
    assert row["per_state"]["e_dp"]["mape"] == pytest.approx(2.0)

    good = {k: (0.01, 0.999) for k in ("jaxdmd_dae", "jaxdmd_de", "oracle_dae", "oracle_de")}
    sindy = {"sindy_accurate": (5.0, 0.5), "sindy_overcomplete": (10.0, -1.0)}
    per = {
        30: _generator(30, good | sindy),
        31: _generator(31, good | sindy, diverged=("sindy_overcomplete",)),
    }
    mean = table1.aggregate(per)
    assert mean["jaxdmd_dae"]["mape"] == pytest.approx(0.01)
    assert mean["jaxdmd_dae"]["rounds"] == pytest.approx(10)
    # a diverged generator makes the mean inf, the finite mean and the median leave it out
    over = mean["sindy_overcomplete"]
    assert over["mape"] == math.inf and over["r2"] == -math.inf and over["n_diverged"] == 1
    assert over["mape_mean_finite"] == pytest.approx(10.0)
    # errored rows are counted, not averaged
    assert mean["sindy_missing"]["n_errors"] == 2 and mean["sindy_missing"]["n_generators"] == 0
    assert math.isnan(mean["sindy_missing"]["mape"])

    goal = table1.goal_check(mean)
    assert goal["mape_met"] and goal["r2_met"] and goal["oracle_met"] and goal["met"]
    worse = _generator(32, {**good, "jaxdmd_dae": (0.2, 0.97)} | sindy)
    goal = table1.goal_check(table1.aggregate({**per, 32: worse}))
    assert not goal["mape_met"] and not goal["r2_met"] and not goal["met"]
    assert goal["mape_vs_oracle"] == pytest.approx((0.01 * 2 + 0.2) / 3 / 0.01)

    assert table1.best_sindy(per[30]["rows"]) == "sindy_accurate"
    result = {
        "mean": mean,
        "goal": table1.goal_check(mean),
        "generators_done": [30, 31],
        "generators": {str(g): v for g, v in per.items()},
        "settings": {"operating_points": 4, "noise": 0.01, "rounds": 15, "seed": 0},
    }
    md = table1.markdown(result)
    assert "| jaxdmd (full DAE) | 0.01 |" in md
    assert "| 31 |" in md and "1/2" in md and "2 errors" in md


def test_replace_section_touches_only_table_i() -> None:
    text = (
        "# Benchmarks\n\nintro\n\n## Speed\n\nfast\n\n"
        "## Table I\n\nold\n### sub\nold2\n\n## Later\n\nkeep\n"
    )
    new = table1.replace_section(text, "## Table I", "| new |\n")
    assert "old" not in new and "| new |" in new
    assert new.index("## Speed") < new.index("## Table I") < new.index("## Later")
    assert new.endswith("## Later\n\nkeep\n") and "fast" in new
    appended = table1.replace_section("# B\n\n## Speed\n\nfast\n", "## Table I", "x\n")
    assert appended == "# B\n\n## Speed\n\nfast\n\n## Table I\n\nx\n"


def test_oracle_skeletons_are_the_true_structure() -> None:
    """With PSAT 5.1's parameters of generator 31 the oracle's equations are the reference's."""
    from jaxdmd.skeleton import compile_skeleton

    truth = table1.oracle_truth(31)
    ae = compile_skeleton(table1.ORACLE_AE_SOURCE, variables=table1.ORACLE_AE_ARGS, n_outputs=3)
    de = compile_skeleton(table1.ORACLE_DE_SOURCE, variables=table1.ORACLE_DE_ARGS, n_outputs=5)
    assert (ae.n_params, de.n_params) == (2, 9)
    ra, xdp, M, Td0 = 0.0027, 0.0697, 60.6, 6.56
    rng = np.random.default_rng(0)
    v = {n: rng.uniform(0.5, 1.2, 50) for n in {*table1.ORACLE_AE_ARGS, *table1.ORACLE_DE_ARGS}}
    i_d, i_q, P_e = np.asarray(ae(v, np.asarray(list(truth["ae"].values()))))
    vd = v["V"] * np.sin(v["delta"] - v["theta"])
    vq = v["V"] * np.cos(v["delta"] - v["theta"])
    # 0 = v_q + r_a i_q - e'_q + x'_d i_d,  0 = v_d + r_a i_d - e''_d - x'_d i_q
    np.testing.assert_allclose(vq + ra * i_q - v["e_qp"] + xdp * i_d, 0, atol=1e-12)
    np.testing.assert_allclose(vd + ra * i_d - v["e_dpp"] - xdp * i_q, 0, atol=1e-12)
    np.testing.assert_allclose(P_e, (vd + ra * i_d) * i_d + (vq + ra * i_q) * i_q, atol=1e-12)
    d = np.asarray(de(v, np.asarray(list(truth["de"].values()))))
    np.testing.assert_allclose(d[0], 2 * np.pi * 60 * (v["omega"] - 1), rtol=1e-12)
    np.testing.assert_allclose(d[1], (v["P_m"] - v["P_e"]) / M, rtol=1e-12)
    expect = (-v["e_qp"] - (0.295 - xdp) * v["i_d"] + v["v_f"]) / Td0
    np.testing.assert_allclose(d[2], expect, rtol=1e-12)
