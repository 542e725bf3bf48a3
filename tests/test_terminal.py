"""Diagnosis from terminal channels alone (V, theta, P, Q, omega: what a PMU records).

Each scenario simulates the IEEE 39-bus system with an effect the PSAT 5.1 model lacks (the
truth lives here, in the test), keeps only generator 31's terminal channels (three bus-15-fault
recordings with noise of 0.5 % of each measured output's range; a clean bus-28 recording held
out), and requires the diagnosis to name the equation and the term, to recover the effect's
size and to pay off on the held-out P and Q.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import equinox as eqx
import numpy as np
import pytest

from jaxdmd.data import Dataset
from jaxdmd.grid import Exciter, Governor, MachineModel
from jaxdmd.grid.machines import machine_params
from jaxdmd.grid.network import case39
from jaxdmd.grid.operating import operating_points
from jaxdmd.grid.protocol import generator_dataset, simulate_each
from jaxdmd.terminal import (
    FAMILIES,
    TerminalConfig,
    candidates,
    diagnose_terminal,
    is_terminal,
    write_terminal_report,
)

GEN = 31
NOISE = 0.005


def terminal_channels(ds: Dataset, noise: float, seed: int) -> Dataset:
    """What a PMU at the terminal records: V, theta, P = v_d i_d + v_q i_q (the power injected
    at the terminal, not the air-gap power), Q and the speed, noise on P, Q and omega."""
    P = np.asarray(ds["v_d"]) * np.asarray(ds["i_d"]) + np.asarray(ds["v_q"]) * np.asarray(
        ds["i_q"]
    )
    channels = {
        "V": np.asarray(ds["V"]),
        "theta": np.asarray(ds["theta"]),
        "P": P,
        "Q": np.asarray(ds["Q_e"]),
        "omega": np.asarray(ds["omega"]),
    }
    rng = np.random.default_rng(seed)
    for name in ("P", "Q", "omega"):
        x = channels[name]
        channels[name] = x + noise * np.ptp(x) * rng.standard_normal(x.size)
    roles = {"V": "boundary", "theta": "boundary", "P": "algebraic", "Q": "algebraic"}
    return Dataset.create(
        np.asarray(ds.t), channels, {**roles, "omega": "algebraic"}, units={"theta": "rad"},
        events=ds.events, label=ds.label,
    )  # fmt: skip


def recordings(model: MachineModel, params=None) -> tuple[list[Dataset], list[Dataset]]:
    ops = operating_points(4, 0, spread=0.3)
    train_run = simulate_each(ops[:3], model, 15, params=params)
    test_run = simulate_each(ops[3:], model, 28, params=params)
    train = [terminal_channels(generator_dataset(train_run, GEN, i), NOISE, i) for i in range(3)]
    return train, [terminal_channels(generator_dataset(test_run, GEN, 0), 0.0, 9)]


def test_terminal_data_are_recognised_and_bad_data_are_clear_errors():
    t = np.linspace(0.0, 2.0, 201)
    ones = np.ones_like(t)
    ds = Dataset.create(
        t, {"V": ones, "theta": 0 * t, "P": ones, "Q": 0 * t},
        {"V": "boundary", "theta": "boundary", "P": "algebraic", "Q": "algebraic"},
    )  # fmt: skip
    assert is_terminal(ds, FAMILIES["psat-5.1"].states)
    with pytest.raises(ValueError, match="no events"):
        diagnose_terminal([ds, ds], "psat-5.1")
    with pytest.raises(ValueError, match="missing Q"):
        diagnose_terminal([ds.select(["V", "theta", "P"])] * 2, "psat-5.1")
    with pytest.raises(ValueError, match="held-out data"):
        diagnose_terminal([ds], "psat-5.1")
    # the candidate pool is generic: every state equation gets the same terms (its own state
    # squared aside), both stator equations the same three
    cands = candidates(FAMILIES["psat-5.1"], measured=("P_m", "v_f"))
    per = {}
    for eq, term in cands:
        per.setdefault(eq, set()).add(term.replace(f"{eq}**2", "own**2"))
    assert per["stator_q"] == per["stator_d"] == {"1", "i_d", "i_q"}
    assert per["e_qp"] == per["e_dp"] == per["e_dpp"] == per["omega"] | {"own**2"}
    # unmeasured P_m and v_f are solved for at the equilibrium: the constants they absorb go
    absorbed = set(cands) - set(candidates(FAMILIES["psat-5.1"]))
    assert absorbed == {("omega", "1"), ("e_qp", "1"), ("stator_q", "1")}


@pytest.fixture(scope="module")
def damping():
    model = MachineModel(damping=30.0)
    return model, *recordings(model)


@pytest.mark.slow
def test_hidden_damping_is_named_from_terminal_channels(damping, tmp_path):
    model, train, test = damping
    result = diagnose_terminal(train, "psat-5.1", test=test)
    cause = result.cause
    assert (cause["equation"], cause["term"], cause["equation_kind"]) == (
        "omega",
        "omega - 1",
        "state",
    ), cause
    g = case39().gen_index(GEN)
    p = machine_params(model)
    M, D = float(p.M[g]), float(p.D[g])
    ext = result.parameters["extended"]
    assert abs(ext["omega - 1 in omega"] / (-D / M) - 1) < 0.05
    assert abs(ext["M"] / M - 1) < 0.02 and abs(ext["x_dp"] / float(p.x_dp[g]) - 1) < 0.02
    held = result.errors["held_out"]
    assert all(held["refit"][o] > 10 * held["extended"][o] for o in ("P", "Q"))
    # P_m and v_f were not measured: said, with what was assumed
    assert any(a.startswith("P_m") and "assumed constant" in a for a in result.assumptions)
    assert any(a.startswith("v_f") for a in result.assumptions)
    path = write_terminal_report(tmp_path, result)
    text = path.read_text()
    assert "lacks a term omega - 1" in text and "Not measured: P_m" in text
    assert (tmp_path / "terminal.png").stat().st_size > 10_000
    saved = json.loads((tmp_path / "diagnosis.json").read_text())
    assert saved["mode"] == "terminal" and saved["gain"]["P"] > 10


@pytest.mark.slow
def test_hidden_stator_saliency_is_named_in_the_algebraic_equations():
    # the d-axis stator equation with its own reactance X_q = x'_d / 2 (the model shares
    # x'_d on both axes); the sub-transient equation follows so that the machine starts at rest
    model = MachineModel()
    p = machine_params(model)
    g = case39().gen_index(GEN)
    x_q = 0.5 * float(p.x_dp[g])
    p = eqx.tree_at(lambda q: q.X_q, p, p.X_q.at[g].set(x_q))
    p = eqx.tree_at(lambda q: q.c_edpp, p, p.c_edpp.at[g].add(float(p.x_dp[g]) - x_q))
    train, test = recordings(model, p)
    result = diagnose_terminal(train, "psat-5.1", test=test)
    cause = result.cause
    assert cause["equation_kind"] == "algebraic", cause
    named = {(cause["equation"], cause["term"])} | {
        (e["equation"], e["term"]) for e in cause["equivalent"]
    }
    assert ("stator_d", "i_q") in named  # or its twin, i_d in the q-axis equation
    ext = result.parameters["extended"]
    # d-axis freed: -x'_d i_q + c i_q, X_q = x'_d - c; q-axis freed: X_d = x'_d + c, X_q = x'_d
    found = ext["x_dp"] - ext.get("i_q in stator_d", 0.0)
    assert abs(found / x_q - 1) < 0.05, (found, x_q)
    held = result.errors["held_out"]
    assert all(held["refit"][o] > 5 * held["extended"][o] for o in ("P", "Q"))


@pytest.mark.slow
def test_cli_diagnoses_terminal_data_and_leaves_the_right_model_alone(tmp_path):
    train, test = recordings(MachineModel())
    paths = [str(ds.save(tmp_path / f"rec{i}.npz")) for i, ds in enumerate([*train, *test])]
    out = tmp_path / "out"
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    done = subprocess.run(
        [sys.executable, "-m", "jaxdmd.run", "diagnose", "--data", *paths[:-1], "--test-data",
         paths[-1], "--model", "psat-5.1", "--out", str(out)],
        capture_output=True, text=True, env=env, timeout=900,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    assert "from terminal channels" in done.stderr
    saved = json.loads((out / "diagnosis.json").read_text())
    assert saved["mode"] == "terminal" and saved["cause"]["kind"] == "none", saved["cause"]
    assert (out / "report.md").exists()
    # the structure is right: the refit recovers the machine's data from P, Q and omega alone
    p = machine_params(MachineModel())
    g = case39().gen_index(GEN)
    fitted = saved["parameters"]["refit"]
    for name, truth in (("M", p.M[g]), ("x_dp", p.x_dp[g]), ("T_dp0", p.T_dp0[g])):
        assert abs(fitted[name] / float(truth) - 1) < 0.03, (name, fitted[name], truth)


@pytest.mark.slow
def test_unmeasured_inputs_that_vary_are_named_with_their_control():
    # a governor (5 % droop, T_g 0.5 s) on a machine whose P_m is not measured: P_m is named
    # as not constant, and the droop and time constant are recovered
    model = MachineModel(governor=Governor())
    g = case39().gen_index(GEN)
    p = machine_params(model)
    train, test = recordings(model)
    result = diagnose_terminal(train, "psat-5.1", test=test)
    cause = result.cause
    assert (cause["kind"], cause["equation"]) == ("missing variable", "P_m"), cause
    assert "P_m" in cause["summary"] and "governor" in cause["summary"]
    ext = result.parameters["extended"]
    assert abs(ext["G"] * float(p.R[g]) - 1) < 0.05  # G = 1 / R
    assert abs(ext["T_g"] / float(p.T_g[g]) - 1) < 0.1
    held = result.errors["held_out"]
    assert all(held["refit"][o] > 10 * held["extended"][o] for o in ("P", "Q"))


@pytest.mark.slow
def test_an_unmeasured_field_voltage_under_a_regulator_is_named_and_its_confounding_said():
    # a voltage regulator (K_A 10, T_A 0.3 s) and v_f not measured: v_f is named; from terminal
    # channels the regulator's gain and T'_d0 are confounded (their ratio is what the data see).
    # The machine also has a damping D = 10 the model lacks: one cause is named, the larger
    model = MachineModel(exciter=Exciter(K_A=10.0, T_A=0.3), damping=10.0)
    g = case39().gen_index(GEN)
    p = machine_params(model)
    train, test = recordings(model)
    # one term: the second round (its best, a governor, does not simulate the held-out data
    # better) takes minutes in the regulator's flat valley and is not what this test checks
    config = TerminalConfig(max_terms=1)
    result = diagnose_terminal(train, "psat-5.1", test=test, config=config)
    cause = result.cause
    assert (cause["kind"], cause["equation"]) == ("missing variable", "v_f"), cause
    ext = result.parameters["extended"]
    truth = float(p.K_A[g]) / float(p.T_dp0[g])
    assert abs(ext["K_A"] / ext["T_dp0"] / truth - 1) < 0.15
    assert "measuring v_f would separate them" in cause["summary"]
    held = result.errors["held_out"]
    assert all(held["refit"][o] > 4 * held["extended"][o] for o in ("P", "Q"))
