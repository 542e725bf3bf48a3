"""The refit by simulation (output error): what equation-error fits leave, the closed model
corrects; what it cannot improve on left-out recordings, it leaves alone."""

from __future__ import annotations

import numpy as np
import pytest
from tracking import tracking

import jaxdmd  # noqa: F401  (float64)
from jaxdmd import interp, search, workers
from jaxdmd.data import Dataset
from jaxdmd.problems import ae_problem, de_problem
from jaxdmd.select import SelectionConfig, dae_errors, simulation_nrmse
from jaxdmd.simfit import _Simulator, refit_finalists, refit_simulation, refit_task

GAIN = 5.0


def _regulator(n: int = 4, noise: float = 0.01) -> list[Dataset]:
    """d x/dt = u - y with y = 5 (x - theta): x follows a slow angle theta, pushed off it by
    u; x is measured with 1 % noise."""
    return tracking(n, noise, GAIN, 501, (0.3, 0.07, 0.5, 0.1), seed=10)


def _equations(recordings: list[Dataset], ae_params: tuple[float, float]):
    _, contract = de_problem(recordings, library=("u", "y", "theta"))
    de = search.Equations(contract, "def f(u, y, p):\n    return p[0] * u + p[1] * y\n",
                          (1.0, -1.0), (0.0,), 0.0)  # fmt: skip
    _, ae_contract = ae_problem(recordings, contract)
    source = "def g(x, theta, p):\n    return p[0] * x + p[1] * theta\n"
    return de, search.Equations(ae_contract, source, ae_params, (0.0,), 0.0)


def test_the_jax_simulation_is_the_host_simulation():
    recordings = _regulator(n=2)
    de, ae = _equations(recordings, (4.0, -4.2))
    sim = _Simulator(de, ae, recordings, recordings, substeps=1, blowup=1e3)
    closed = sim.errors(np.asarray(sim.theta0))[0]
    program = interp.program_of(ae.skeleton())
    for b, ds in enumerate(recordings):
        host = dae_errors(de, program, ae.contract.targets, np.asarray(ae.params), [ds],
                          SelectionConfig())  # fmt: skip
        np.testing.assert_allclose(closed[b], host[0], rtol=1e-9)


def test_an_algebraic_bias_the_closed_model_exposes_is_refitted():
    """An AE equation whose gains are off by 10 % and 8 % (what an equation-error fit on
    estimated states can leave) simulates the closed model 5x worse than the truth; fitted to
    the simulations, the gains of the data come back."""
    recordings = _regulator()
    de, ae = _equations(recordings, (4.5, -4.6))
    de_new, ae_new, report = refit_simulation(de, ae, recordings)
    assert report["kept"] == "refit", report
    assert report["loro"]["refit"] < 0.6 * report["loro"]["given"]
    after, before = report["nrmse"]["after"], report["nrmse"]["before"]
    assert after["closed"] < 0.3 * before["closed"]
    assert after["played_in"] <= before["played_in"]
    assert ae_new.params == pytest.approx((GAIN, -GAIN), rel=0.01)
    assert de_new.params == pytest.approx((1.0, -1.0), rel=0.02)


def test_a_model_that_cannot_be_improved_is_kept():
    recordings = _regulator()
    de, ae = _equations(recordings, (GAIN, -GAIN))
    de_new, ae_new, report = refit_simulation(de, ae, recordings)
    assert report["kept"].startswith("given"), report
    assert (de_new, ae_new) == (de, ae)
    assert report["held_out"] == "recordings"


def _residual(sim: _Simulator, theta, weight):
    """The refit's residual from the full rollouts: each sample's error scaled by its
    state's range and sqrt(n), times ``weight`` ``[B, n]``, both simulations."""
    import jax.numpy as jnp

    n = sim.y.shape[2]
    scaled = [(x - sim.y) / sim.scale[:, :, None] / np.sqrt(n) for x in sim.simulate(theta)]
    return jnp.concatenate([(r * weight[:, None, :]).ravel() for r in scaled])


def test_the_fits_factor_is_that_of_the_residual_and_its_jacobian(monkeypatch):
    """The fit never forms the residual's Jacobian: it folds the sensitivities into a QR
    factor a chunk of sample intervals at a time. Chunks of 7 intervals (the last one padded)
    and a block of samples weighted out: the factor holds the normal equations and the sum of
    squares of the Jacobian and the residual it stands for."""
    import jax
    import jax.numpy as jnp

    from jaxdmd import simfit

    monkeypatch.setattr(simfit, "_CHUNK", 7)
    recordings = _regulator(n=2)
    de, ae = _equations(recordings, (4.5, -4.6))
    sim = _Simulator(de, ae, recordings, recordings, substeps=2, blowup=1e3)
    theta = jnp.asarray(sim.theta0) * 1.1
    weight = np.ones((2, recordings[0].n_samples))
    weight[1, 100:250] = 0.0
    r = np.asarray(_residual(sim, theta, jnp.asarray(weight)))
    J = np.asarray(jax.jacfwd(_residual, argnums=1)(sim, theta, jnp.asarray(weight)))
    f = np.asarray(sim.factor(weight)(theta))
    p = theta.size
    R, z, rho = f[:p, :p], f[:p, p], f[p, p]
    np.testing.assert_allclose(R.T @ R, J.T @ J, rtol=1e-12, atol=1e-14 * np.abs(J.T @ J).max())
    np.testing.assert_allclose(R.T @ z, J.T @ r, rtol=1e-12, atol=1e-14 * np.abs(J.T @ r).max())
    assert z @ z + rho**2 == pytest.approx(r @ r, rel=1e-12)


def test_the_fits_working_memory_does_not_depend_on_the_length():
    """The compiled fold's temporary memory (XLA's own count) is the same for recordings of
    501 and 5001 samples: a Jacobian of the rollouts would grow tenfold."""
    import jax.numpy as jnp

    temp = []
    for samples in (501, 5001):
        recordings = tracking(4, 0.01, GAIN, samples, (0.3, 0.07, 0.5, 0.1), seed=10)
        de, ae = _equations(recordings, (4.5, -4.6))
        sim = _Simulator(de, ae, recordings, recordings, substeps=1, blowup=1e3)
        theta = jnp.asarray(sim.theta0)
        program = sim._folded.lower(theta, *sim._fold_inputs(np.ones((4, 1))))
        temp.append(program.compile().memory_analysis().temp_size_in_bytes)
    assert temp[1] <= 1.05 * temp[0], temp


def test_the_jax_simulation_of_time_blocks_is_the_host_simulation():
    from jaxdmd.select import time_blocks

    recordings = _regulator(n=1)
    de, ae = _equations(recordings, (4.0, -4.2))
    blocks = time_blocks(np.asarray(recordings[0].t))
    sim = _Simulator(de, ae, recordings * 4, recordings * 4, 1, 1e3, windows=blocks)
    closed = sim.errors(np.asarray(sim.theta0))[0]  # [blocks, S]
    program = interp.program_of(ae.skeleton())
    host = dae_errors(de, program, ae.contract.targets, np.asarray(ae.params), recordings * 4,
                      SelectionConfig(), windows=blocks)  # fmt: skip
    np.testing.assert_allclose(closed, host, rtol=1e-9)


def test_one_recording_the_refit_is_checked_on_held_out_time_blocks():
    """With one recording the refit is left out block by block: the biased AE gains are
    refitted to the data's, and a model that is the truth is left alone (an output-error fit
    never raises its in-sample error, whatever the start; on held-out blocks it does not
    help)."""
    recordings = _regulator()[:1]
    de, ae = _equations(recordings, (4.5, -4.6))
    de_new, ae_new, report = refit_simulation(de, ae, recordings)
    assert report["held_out"] == "time blocks (4)"
    assert report["kept"] == "refit", report
    assert len(report["loro"]["per_block"]) == 4
    assert report["loro"]["refit"] < 0.5 * report["loro"]["given"]
    assert report["nrmse"]["after"]["closed"] < 0.3 * report["nrmse"]["before"]["closed"]
    assert ae_new.params == pytest.approx((GAIN, -GAIN), rel=0.02)
    assert de_new.params == pytest.approx((1.0, -1.0), rel=0.02)
    de, ae = _equations(recordings, (GAIN, -GAIN))
    de_new, ae_new, report = refit_simulation(de, ae, recordings)
    assert report["kept"] == "given: the refit does not simulate left-out time blocks (4) better"
    assert (de_new, ae_new) == (de, ae)


def _stand_in(recordings: list[Dataset], contract) -> search.Equations:
    """y = a x + b u fitted to y by least squares (an equation-error fit): the input u stands
    in for the slow angle theta the truth has."""
    x, u, y = (np.concatenate([np.asarray(ds[c]) for ds in recordings]) for c in ("x", "u", "y"))
    a, b = np.linalg.lstsq(np.stack([x, u], 1), y, rcond=None)[0]
    source = "def g(x, u, p):\n    return p[0] * x + p[1] * u\n"
    return search.Equations(contract, source, (float(a), float(b)), (0.0,), 0.0)


def test_the_structure_that_simulates_best_once_refitted_is_the_model():
    """The true structure with the gains an equation-error fit can leave (2.0, -2.2 for 5, -5)
    simulates the closed model worse than a stand-in fitted by least squares (u for theta):
    judged by its parameters as given, the stand-in wins. Refitted to simulate, the truth
    simulates left-out recordings 10x better than the stand-in can: it is the model, with the
    data's gains; listed first, it stays the model."""
    recordings = _regulator()
    de, truth = _equations(recordings, (2.0, -2.2))
    stand_in = _stand_in(recordings, truth.contract)
    assert simulation_nrmse(de, recordings, stand_in) < simulation_nrmse(de, recordings, truth)
    _, ae_new, report = refit_finalists(de, [("stand-in", stand_in), ("truth", truth)], recordings)
    assert report["chosen"] == "truth", report["finalists"]
    errors = {f["name"]: f["held_out_nrmse"] for f in report["finalists"]}
    assert errors["truth"] < 0.1 * errors["stand-in"]
    assert report["kept"] == "refit"
    assert ae_new.params == pytest.approx((GAIN, -GAIN), rel=0.01)
    _, _, report = refit_finalists(de, [("truth", truth), ("stand-in", stand_in)], recordings)
    assert report["chosen"] == "truth"


def test_a_finalist_replaces_the_preferred_one_only_when_clearly_better():
    """The truth and the truth with a stand-in added (u, fitted by least squares) simulate
    left-out recordings alike once refitted: whichever is listed first stays the model. A
    finalist that differs from an earlier one only in its parameters is not refitted (the
    refit fits them); no finalist at all is an error."""
    recordings = _regulator()
    de, truth = _equations(recordings, (GAIN, -GAIN))
    x, u, theta, y = (
        np.concatenate([np.asarray(ds[c]) for ds in recordings]) for c in ("x", "u", "theta", "y")
    )
    p = np.linalg.lstsq(np.stack([x, theta, u], 1), y, rcond=None)[0]
    source = "def g(x, theta, u, p):\n    return p[0] * x + p[1] * theta + p[2] * u\n"
    extra = search.Equations(truth.contract, source, tuple(map(float, p)), (0.0,), 0.0)
    _, _, report = refit_finalists(de, [("truth", truth), ("extra", extra)], recordings)
    errors = [f["held_out_nrmse"] for f in report["finalists"]]
    assert errors[1] == pytest.approx(errors[0], rel=0.05)
    assert report["chosen"] == "truth"
    _, _, report = refit_finalists(de, [("extra", extra), ("truth", truth)], recordings)
    assert report["chosen"] == "extra"
    _, other = _equations(recordings, (4.9, -5.1))
    _, _, report = refit_finalists(de, [("first", truth), ("second", other)], recordings)
    assert report["chosen"] == "first"
    assert report["finalists"][1]["kept"].startswith("not refitted"), report["finalists"]
    with pytest.raises(ValueError):
        refit_finalists(de, [], recordings)


def test_a_finalist_refitted_in_a_worker_process_is_the_finalist_refitted_here():
    """The stand-in's refit started in a worker process (beside other work, as discover does)
    gives the choice and the numbers of the refit here; a worker that fails is replaced by the
    refit here, and the report says so."""
    recordings = _regulator()
    de, truth = _equations(recordings, (2.0, -2.2))
    stand_in = _stand_in(recordings, truth.contract)
    finalists = [("truth", truth), ("stand-in", stand_in)]
    here = refit_finalists(de, finalists, recordings)
    worker = workers.start(refit_task, de, stand_in, recordings, None, None)
    away = refit_finalists(de, finalists, recordings, started={"stand-in": worker.result})
    assert away[1] == here[1] and away[0] == here[0]
    assert away[2]["finalists"] == here[2]["finalists"]

    def broken():
        raise workers.WorkerError("exit status 9")

    again = refit_finalists(de, finalists, recordings, started={"stand-in": broken})
    assert again[1] == here[1]
    failed = again[2]["finalists"][1]
    assert failed.pop("worker_failed") == "exit status 9"
    assert again[2]["finalists"] == here[2]["finalists"]
