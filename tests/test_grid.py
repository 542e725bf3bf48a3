"""Tests of the IEEE 39-bus benchmark simulator (jaxdmd.grid)."""

from __future__ import annotations

import argparse
import contextlib
import io
import subprocess
import sys
import warnings

import numpy as np
import pytest
from jax import tree_util

import jaxdmd  # noqa: F401  (enables float64)
from jaxdmd.grid import (
    STATE_LAYOUT,
    Exciter,
    Fault,
    Governor,
    MachineModel,
    SynchronismWarning,
    case39,
    machine_params,
    nominal_operating_point,
    operating_points,
    out_of_step,
    paper_protocol,
    simulate,
)

GEN_BUSES = tuple(range(30, 40))


@pytest.fixture(scope="module")
def op():
    return nominal_operating_point()


@pytest.fixture(scope="module")
def fault15(op):
    return simulate(op, "psat-5.1", 15)


@pytest.fixture(scope="module")
def fault28(op):
    return simulate(op, "psat-5.1", 28)


@pytest.fixture(scope="module")
def protocol():
    return paper_protocol(n_train=2, n_test=2, seed=3, noise=0.01, generators=(31, 39))


# -- network and operating points -----------------------------------------------------------


def test_power_flow_matches_pypower(op):
    from pypower.api import ppoption, runpf
    from pypower.case39 import case39 as ppc39

    with contextlib.redirect_stdout(io.StringIO()):
        r, ok = runpf(ppc39(), ppoption(VERBOSE=0, OUT_ALL=0))
    assert ok
    np.testing.assert_allclose(np.asarray(op.Vm), r["bus"][:, 7], atol=1e-6, rtol=0)
    np.testing.assert_allclose(np.rad2deg(np.asarray(op.Va)), r["bus"][:, 8], atol=1e-6, rtol=0)
    np.testing.assert_allclose(np.asarray(op.Pg) * 100, r["gen"][:, 1], atol=1e-6)
    np.testing.assert_allclose(np.asarray(op.Qg) * 100, r["gen"][:, 2], atol=1e-6)


def test_operating_points_reproducible_and_in_range(protocol):
    pts = protocol.train_points
    f = np.asarray(pts.load_factors)
    assert f.shape == (2, 39) and f.min() >= 0.7 and f.max() <= 1.3
    again = operating_points(2, 3)
    np.testing.assert_array_equal(np.asarray(again.Vm), np.asarray(pts.Vm))
    np.testing.assert_allclose(np.asarray(pts.Pd), case39().Pd * f)
    assert not np.allclose(np.asarray(pts.Pg[0]), np.asarray(pts.Pg[1]))


def test_bad_input_errors():
    with pytest.raises(ValueError, match="unknown bus"):
        Fault(bus=40)
    with pytest.raises(ValueError, match="unknown machine model"):
        MachineModel("psat-6.2")
    with pytest.raises(ValueError, match="no generator at bus"):
        case39().gen_index(15)
    with pytest.raises(ValueError, match="t_on"):
        Fault(bus=15, t_on=1.2, t_off=1.1)
    with pytest.raises(ValueError, match="classical"):
        MachineModel("classical", exciter=Exciter())


# -- simulation --------------------------------------------------------------------------------


def test_output_shapes(fault15):
    r = fault15
    assert r.t.shape == (1001,) and float(r.t[-1]) == pytest.approx(10.0)
    assert r.x.shape == (1001, 7, 10) and r.dx.shape == (1001, 7, 10)
    assert r.bus_V.shape == (1001, 39)
    assert np.all(np.isfinite(np.asarray(r.x)))


@pytest.mark.parametrize(
    "model",
    [
        MachineModel(),
        MachineModel("two-axis"),
        MachineModel("one-axis"),
        MachineModel("classical"),
        MachineModel(damping=2.0, saturation=(0.05, 0.2)),
        MachineModel(exciter=Exciter(), governor=Governor(), damping=1.0),
        MachineModel("one-axis", exciter=Exciter(), governor=Governor()),
    ],
    ids=["5.1", "two-axis", "one-axis", "classical", "D+sat", "avr+gov", "one-axis+ctrl"],
)
def test_undisturbed_run_stays_at_rest(op, model):
    r = simulate(op, model, None)
    dx = np.asarray(r.dx)
    assert np.abs(dx).max() < 1e-6
    np.testing.assert_allclose(np.asarray(r.alg["V"])[-1], np.asarray(op.Vm)[30 - 1 :], atol=1e-7)


def test_stator_equations_hold_along_fault_run(fault15):
    p = machine_params("psat-5.1")
    a = {k: np.asarray(v) for k, v in fault15.alg.items()}
    x = np.asarray(fault15.x)
    ra, xdp = np.asarray(p.r_a), np.asarray(p.x_dp)
    eqp, edpp, delta = x[:, 2], x[:, 4], x[:, 0]
    r1 = a["v_q"] + ra * a["i_q"] - eqp + xdp * a["i_d"]
    r2 = a["v_d"] + ra * a["i_d"] - edpp - xdp * a["i_q"]
    assert np.abs(r1).max() < 1e-8 and np.abs(r2).max() < 1e-8
    np.testing.assert_allclose(a["v_d"], a["V"] * np.sin(delta - a["theta"]), atol=1e-8)
    np.testing.assert_allclose(a["v_q"], a["V"] * np.cos(delta - a["theta"]), atol=1e-8)
    pe = (a["v_d"] + ra * a["i_d"]) * a["i_d"] + (a["v_q"] + ra * a["i_q"]) * a["i_q"]
    np.testing.assert_allclose(a["P_e"], pe, atol=1e-10)
    # the exact derivatives obey the swing equation
    M = np.asarray(p.M)
    np.testing.assert_allclose(
        np.asarray(fault15.derivative("omega")), (a["P_m"] - a["P_e"]) / M, atol=1e-10
    )


@pytest.mark.parametrize("which", ["fault15", "fault28"])
def test_faulted_bus_voltage_near_zero(which, request):
    r = request.getfixturevalue(which)
    bus = r.fault.bus
    t = np.asarray(r.t)
    V = np.asarray(r.bus_V)[:, bus - 1]
    during = (t >= 1.0 - 1e-9) & (t < 1.1 - 1e-9)
    assert during.sum() == 10
    assert V[during].max() < 0.02
    assert V[t < 1.0 - 1e-9].min() > 0.9
    assert V[t > 1.5].min() > 0.8


@pytest.mark.parametrize("which", ["fault15", "fault28"])
def test_all_machines_stay_in_step(which, request):
    r = request.getfixturevalue(which)
    d = np.asarray(r.state("delta"))
    w = np.asarray(r.state("omega"))
    M = np.asarray(machine_params().M)
    coi = (d * M).sum(1, keepdims=True) / M.sum()
    rel = d - coi
    assert np.abs(rel - rel[0]).max() < 1.5  # rad: no machine slips a pole
    w_coi = (w * M).sum(1, keepdims=True) / M.sum()
    assert np.abs(w - w_coi)[-100:].max() < 5e-3  # speeds stay together
    assert np.abs(w - 1).max() < 0.05
    assert out_of_step(r) == [()]


def test_protocol_data_are_stable(protocol):
    assert protocol.stable
    assert protocol.out_of_step == {"train": [(), ()], "test": [(), ()]}


def test_loss_of_synchronism_is_detected_and_warned():
    """The one-axis machines with saturation and the default AVR (K_A 20, T_A 0.2 s) slip poles
    after the bus-15 fault (the set-up tests/test_diagnose.py used before): paper_protocol warns,
    naming the recording, and says so in out_of_step; a slow, low-gain AVR keeps them in step."""
    slipping = MachineModel(name="one-axis", saturation=(0.1, 0.3), exciter=Exciter())
    with pytest.warns(SynchronismWarning, match=r"train point 0 \(seed 0, fault bus 15\): gen"):
        data = paper_protocol(
            n_train=1, n_test=0, seed=0, noise=0.0, model=slipping, generators=[31]
        )
    assert not data.stable and 31 in data.out_of_step["train"][0]
    omega = np.asarray(data.train_result.state("omega"))
    assert np.ptp(omega) > 0.1  # pu: the speeds run away
    # simulate() warns by itself too
    with pytest.warns(SynchronismWarning, match="fault at bus 15"):
        simulate(data.train_points[0], slipping, 15)
    steady = MachineModel(
        name="one-axis", saturation=(0.1, 0.3), exciter=Exciter(K_A=10.0, T_A=0.5)
    )
    with warnings.catch_warnings():
        warnings.simplefilter("error", SynchronismWarning)
        data = paper_protocol(n_train=1, n_test=0, seed=0, noise=0.0, model=steady, generators=[31])
    assert data.stable


def test_derivative_matches_finite_differences(fault15):
    t = np.asarray(fault15.t)
    x = np.asarray(fault15.state("delta"))
    dx = np.asarray(fault15.derivative("delta"))
    seg = (t > 2.0) & (t < 9.0)
    fd = np.gradient(x, t, axis=0)
    assert np.abs(fd[seg] - dx[seg]).max() < 1e-2 * np.abs(dx[seg]).max()


_VMAP_SCRIPT = """
import numpy as np
import jaxdmd
from jaxdmd.grid import operating_points, simulate
ops = operating_points(2, seed=3)
batch = simulate(ops, "psat-5.1", 15)
# a vmapped batch shares one step sequence (the union of the runs' steps): agreement is to the
# solver's tolerance (rtol 1e-9), not to the last bit
for i in range(2):
    single = simulate(ops[i], "psat-5.1", 15)
    assert np.abs(np.asarray(batch.x[i]) - np.asarray(single.x)).max() < 1e-7
    assert np.abs(np.asarray(batch.alg["P_e"][i]) - np.asarray(single.alg["P_e"])).max() < 1e-7
print("vmap ok")
"""


def test_vmap_equals_single_runs():
    """vmap over operating points gives the single runs' results.

    In a subprocess with a time limit: jax 0.10.2's CPU runtime now and then never signals the
    completion of the vmapped diffrax solve (a hang at 0 % CPU; see jaxdmd/grid/protocol.py),
    which must cost this test a retry, not the whole CI run.
    """
    for _ in range(3):
        try:
            out = subprocess.run(
                [sys.executable, "-c", _VMAP_SCRIPT], capture_output=True, text=True, timeout=150
            )
        except subprocess.TimeoutExpired:
            continue
        assert out.returncode == 0, out.stderr[-3000:]
        assert "vmap ok" in out.stdout
        return
    pytest.fail("the vmapped simulation hung three times")


# -- datasets ----------------------------------------------------------------------------------


def test_paper_protocol_datasets(protocol):
    ds = protocol.train[31][0]
    clean = protocol.train_clean[31][0]
    test = protocol.test[39][1]
    assert ds.state_names == ("delta", "omega", "e_qp", "e_dp", "e_dpp")
    assert ds.algebraic_names == ("i_d", "i_q", "P_e", "Q_e", "v_d", "v_q")
    assert ds.input_names == ("P_m", "v_f") and ds.boundary_names == ("V", "theta")
    assert ds.events == (1.0, 1.1) and test.events == (1.0, 1.1)
    assert ds.n_samples == 1001
    # noise only on the states, sigma = 1 % of the range
    for nm in ds.names:
        diff = ds[nm] - clean[nm]
        if nm in ds.state_names:
            rel = np.std(diff) / np.ptp(clean[nm])
            assert 0.007 < rel < 0.013, (nm, rel)
        else:
            np.testing.assert_array_equal(diff, 0.0)
    exact = protocol.train_exact_derivatives[31][0]
    np.testing.assert_array_equal(clean.derivative("omega"), exact["omega"])
    # test data: the bus-28 fault, clean
    assert "fault bus 28" in test.label
    assert protocol.test_result.fault.bus == 28


def test_the_test_part_alone_is_the_test_part_of_the_whole_protocol(protocol):
    """``parts=("test",)`` (what the command line simulates in a worker while it simulates the
    training part): the same operating points and recordings as the whole protocol's, bit for
    bit, and nothing of the training part."""
    alone = paper_protocol(
        n_train=2, n_test=2, seed=3, noise=0.01, generators=(31, 39), parts=("test",)
    )
    assert alone.train == {31: [], 39: []} and alone.train_points is None
    assert alone.train_result is None
    points = (alone.test_points, protocol.test_points)
    for a, b in zip(*(tree_util.tree_leaves(p) for p in points), strict=True):
        np.testing.assert_array_equal(a, b)
    for g in (31, 39):
        for mine, theirs in zip(alone.test[g], protocol.test[g], strict=True):
            assert mine.label == theirs.label and mine.names == theirs.names
            np.testing.assert_array_equal(mine.values, theirs.values)
            np.testing.assert_array_equal(mine.derivatives, theirs.derivatives)
    with pytest.raises(ValueError, match="parts"):
        paper_protocol(n_train=1, n_test=1, parts=("validation",))


def test_simulate_cli(tmp_path):
    from jaxdmd.data import Dataset
    from jaxdmd.grid.cli import add_simulate_arguments, run_simulate

    parser = argparse.ArgumentParser()
    add_simulate_arguments(parser)
    out = tmp_path / "run.csv"
    args = parser.parse_args(["--fault-bus", "15", "--generator", "31", "--out", str(out)])
    assert run_simulate(args) == 0
    ds = Dataset.load(out)
    assert ds.state_names == ("delta", "omega", "e_qp", "e_dp", "e_dpp")
    assert ds.n_samples == 1001
    bad = parser.parse_args(["--fault-bus", "99", "--out", str(out)])
    with pytest.raises(ValueError, match="unknown bus"):
        run_simulate(bad)


def test_state_layout_is_documented():
    assert STATE_LAYOUT == ("delta", "omega", "e_qp", "e_dp", "e_dpp", "v_f", "P_m")
    assert case39().gen_bus_numbers == GEN_BUSES
