"""Tests of benchmarks/table1.py: aggregation, goal check, the docs section, the oracle skeleton,
the pooled table over seeds and the (generator, seed) jobs."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from benchmark_scripts import load_script

import jaxdmd  # noqa: F401  (float64)

table1 = load_script("table1.py", "table1")


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
    assert (ae.n_params, de.n_params) == (6, 9)
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


def test_oracle_lines_have_their_own_parameters() -> None:
    """The pipeline's AE refits work line by line: each oracle AE line owns its (r_a K, x'_d K)."""
    from jaxdmd import lines as ln

    lines, mappings = ln.split_lines(table1.ORACLE_AE_SOURCE)
    assert [line.n_params for line in lines] == [2, 2, 2]
    assert mappings == ((0, 1), (2, 3), (4, 5))
    assert len(table1.ORACLE_AE_PARAMS) == 6
    truth = table1.oracle_truth(31)["ae"]
    assert list(truth.values())[:2] == list(truth.values())[2:4] == list(truth.values())[4:]


def test_oracle_contracts_roles() -> None:
    roles = {"i_d": "algebraic", "i_q": "algebraic", "P_e": "algebraic", "P_m": "input"}
    roles |= {"v_f": "input", "V": "boundary", "theta": "boundary"}

    class Recording:
        def role(self, name: str) -> str:
            return "state" if name in table1.STATES else roles[name]

        def unit(self, name: str) -> str:
            return "pu"

    de, ae = table1.oracle_contracts(Recording())
    assert de.loop == "DE" and de.targets == table1.STATES
    assert de.arguments == table1.ORACLE_DE_ARGS and ae.arguments == table1.ORACLE_AE_ARGS
    assert [v.role for v in de.library] == ["algebraic"] * 3 + ["input"] * 2
    assert ae.loop == "AE" and ae.targets == table1.ORACLE_AE_TARGETS
    assert [(v.name, v.role) for v in ae.library] == [("V", "boundary"), ("theta", "boundary")]
    assert ae.outputs == ("i_d_", "i_q_", "P_e_")


def _seed(values: dict[int, tuple[float, float]], diverged=(), errors=()) -> dict:
    out = {}
    for gen, (m, r) in values.items():
        rows = {k: (m, r) for k in ("jaxdmd_dae", "jaxdmd_de", "oracle_dae")}
        g = _generator(
            gen, {} if gen in errors else rows, diverged=("jaxdmd_dae",) if gen in diverged else ()
        )
        out[gen] = g
    return out


def test_pool_and_acceptance() -> None:
    good = _seed({30: (0.1, 0.99), 31: (0.2, 0.98)})
    ok = _seed({30: (0.1, 0.99), 31: (0.2, 0.98)})
    above = _seed({30: (0.05, 0.99), 31: (1.5, 0.99)})  # mean 0.775 %, one above 1 %
    pooled = table1.pool({0: good, 1: ok})
    assert pooled["n_pairs"] == 4 and pooled["seeds"] == [0, 1]
    assert pooled["mean"]["jaxdmd_dae"]["mape"] == pytest.approx(0.15)
    assert pooled["mean"]["jaxdmd_dae"]["mape_median"] == pytest.approx(0.15)
    per = pooled["per_seed"]["0"]["jaxdmd_dae"]
    assert per["mape"] == pytest.approx(0.15) and per["r2"] == pytest.approx(0.985)
    assert per["n_bad"] == 0 and per["n_generators"] == 2
    assert pooled["acceptance"]["met"]
    assert pooled["cells"]["1"]["31"]["mape"] == pytest.approx(0.2)

    pooled = table1.pool({0: good, 2: above})
    acc = pooled["acceptance"]
    assert acc["per_seed"]["0"]["met"] and not acc["per_seed"]["2"]["met"]
    assert not acc["per_seed"]["2"]["mape_met"] and acc["per_seed"]["2"]["r2_met"]
    assert pooled["per_seed"]["2"]["jaxdmd_dae"]["above_max_mape"] == [31]
    assert not acc["met"]

    # a diverged generator fails its seed even with good means elsewhere; an error too
    div = _seed({30: (0.1, 0.99), 31: (0.1, 0.99)}, diverged=(31,))
    err = _seed({30: (0.1, 0.99), 31: (0.1, 0.99)}, errors=(31,))
    pooled = table1.pool({0: good, 3: div, 4: err})
    s3, s4 = pooled["per_seed"]["3"]["jaxdmd_dae"], pooled["per_seed"]["4"]["jaxdmd_dae"]
    assert s3["diverged"] == [31] and s3["mape"] == math.inf
    assert s4["errors"] == [31] and s4["mape"] == pytest.approx(0.1)
    assert pooled["acceptance"]["per_seed"]["0"]["met"]
    assert not pooled["acceptance"]["per_seed"]["3"]["met"]
    assert not pooled["acceptance"]["per_seed"]["4"]["none_bad"]
    assert pooled["cells"]["4"]["31"] == {"error": "RuntimeError: boom"}
    assert pooled["mean"]["jaxdmd_dae"]["n_errors"] == 1
    assert pooled["mean"]["jaxdmd_dae"]["n_generators"] == 5  # pairs scored

    result = {
        "settings": {"operating_points": 4, "noise": 0.01, "rounds": 15, "jobs": 2},
        **pooled,
        "wall_time_s": 12.0,
    }
    md = table1.pooled_markdown(result)
    assert "Pooled over 6 (generator, seed) pair(s): seeds 0, 3, 4" in md
    assert "| jaxdmd (full DAE) |" in md and "**missed**" in md
    assert (
        "| 3 | 2 | inf | -inf |" in md
        and "| 31 | 0.2 / 0.98 | inf / -inf (diverged) | error |" in md
    )
    assert "with 2 job(s)" in md


def test_algebraic_test_r2_per_seed_against_the_oracle() -> None:
    """The algebraic equations' test R^2 per seed: the default generator's value, the median
    and minimum over the generators, for jaxdmd and both oracles; a generator without a value
    (an oracle that failed) is left out, not counted as zero."""

    def gen(jax_iq: float, oracle_iq: float | None) -> dict:
        oracle = {} if oracle_iq is None else {"ae_test_r2": {"i_d": 1.0, "i_q": oracle_iq}}
        return {
            "rows": {},
            "discovery": {"ae": {"test_r2": {"i_d": 0.9999, "i_q": jax_iq, "P_e": 0.999}}},
            "oracle": oracle,
            "oracle_plain": {"ae_test_r2": {"error": "RuntimeError: boom"}},
        }

    summary = table1.ae_r2_summary({30: gen(0.5, 0.4), 31: gen(0.997, 0.998), 32: gen(0.99, None)})
    iq = summary["i_q"]
    assert iq["jaxdmd"]["default_generator"] == pytest.approx(0.997)
    assert iq["jaxdmd"]["median"] == pytest.approx(0.99) and iq["jaxdmd"]["min"] == 0.5
    assert iq["oracle"]["n"] == 2 and iq["oracle"]["median"] == pytest.approx(0.699)
    assert iq["oracle_plain"] == {"default_generator": None, "median": None, "min": None, "n": 0}
    assert summary["P_e"]["oracle"]["n"] == 0
    md = "\n".join(table1.ae_r2_markdown({"2": summary}))
    assert "| 2 | i_q | 0.99700 | 0.99000 (0.5000) | 0.99800 | 0.69900 (0.4000) | - | - (-) |" in md


def test_a_pair_resumes_as_a_run_of_its_settings() -> None:
    """A pair's run.json, restored as ``jaxdmd discover --resume`` restores it, gives the
    run the pair's generator and seed and the discovery settings the pair ran with."""
    import dataclasses

    from jaxdmd.run import RUN_KEYS, build_parser, config_from_args, restore

    args = table1.build_parser().parse_args(["--out", "x", "--rounds", "7", "--seed", "3"])
    saved = table1.run_settings(33, args)
    assert set(saved) <= set(RUN_KEYS)
    run = build_parser().parse_args(["discover"])
    restore(run, saved)
    assert (run.generator, run.seed, run.rounds) == (33, 3, 7)
    pair = table1.discovery_config(args)
    assert dataclasses.replace(config_from_args(run), jobs=pair.jobs) == pair


def test_jobs_and_layout(tmp_path: Path) -> None:
    out = tmp_path / "t1"
    assert table1.seed_folder(out, 2, multi=True) == out / "seed2"
    assert table1.seed_folder(out, 2, multi=False) == out
    jobs = table1.plan_jobs(out, [30, 31], [0, 1], multi=True, resume=False)
    assert jobs == [(30, 0), (31, 0), (30, 1), (31, 1)]
    # --resume leaves out the pairs done (and only those)
    gens = out / "seed1" / "generators"
    gens.mkdir(parents=True)
    (gens / "gen30.json").write_text('{"status": "done", "generator": 30}')
    (gens / "gen31.json").write_text('{"status": "failed", "generator": 31}')
    assert table1.plan_jobs(out, [30, 31], [0, 1], multi=True, resume=True) == [
        (30, 0),
        (31, 0),
        (31, 1),
    ]
    assert table1.plan_jobs(out, [30, 31], [0, 1], multi=True, resume=False) == jobs
    assert table1.finished(out / "seed1").keys() == {30}
    # a single --seed keeps today's layout: files directly in --out
    (out / "generators").mkdir()
    (out / "generators" / "gen31.json").write_text('{"status": "done", "generator": 31}')
    assert table1.plan_jobs(out, [30, 31], [5], multi=False, resume=True) == [(30, 5)]

    # the worker's command line repeats the settings that change the results
    argv = ["--out", str(out), "--seeds", "0", "1", "--jobs", "2", "--rounds", "3"]
    argv += ["--integral", "0.5", "--no-recombine", "--quiet-rounds", "--noise", "0.02"]
    args = table1.build_parser().parse_args(argv)
    cmd = table1.worker_command(args, 31, 1, out / "seed1", out / ".data" / "seed1" / "gen31")
    assert cmd[1].endswith("table1.py") and "--worker" in cmd
    child = table1.build_parser().parse_args(cmd[2:])
    assert child.worker and child.generators == [31] and child.seed == 1
    assert child.out == str(out / "seed1") and child.seeds is None and child.jobs == 1
    # a pair beside others searches one search at a time; alone, on every core
    assert table1.discovery_config(child).jobs == 1
    assert table1.discovery_config(args).jobs is None
    for key in table1.SETTING_KEYS:
        if key != "seed":
            assert getattr(child, key) == getattr(args, key), key
    assert child.quiet_rounds

    env = table1.child_environment({"PATH": "/bin", "OMP_NUM_THREADS": "8"}, jobs=2)
    assert env["JAX_PLATFORMS"] == "cpu" and env["PATH"] == "/bin"
    assert all(env[v] == "1" for v in table1.THREAD_VARIABLES)
    env = table1.child_environment({"OMP_NUM_THREADS": "8"}, jobs=1)
    assert env["OMP_NUM_THREADS"] == "8" and "OPENBLAS_NUM_THREADS" not in env


def test_recordings_round_trip(tmp_path: Path) -> None:
    """The parent saves a seed's recordings, a worker reads them back exactly."""
    from jaxdmd.data import Dataset

    t = np.linspace(0.0, 1.0, 11)
    ds = Dataset.create(
        t,
        [("delta", np.sin(t)), ("V", np.cos(t))],
        {"delta": "state", "V": "boundary"},
        events=(0.3, 0.5),
        label="x",
    )
    table1.save_recordings(tmp_path, [ds, ds], [ds], 12.5)
    train, test, seconds = table1.load_recordings(tmp_path)
    assert len(train) == 2 and len(test) == 1 and seconds == 12.5
    for a in (*train, *test):
        assert a.names == ds.names and a.events == ds.events and a.label == "x"
        np.testing.assert_array_equal(np.asarray(a.values), np.asarray(ds.values))
        np.testing.assert_array_equal(np.asarray(a.derivatives), np.asarray(ds.derivatives))
