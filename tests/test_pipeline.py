"""Discovery as a library: ``jaxdmd.discover`` without argparse, ``Discovery`` save / load /
simulate / score, and the config's checks."""

from __future__ import annotations

import dataclasses

import jax
import numpy as np
import pytest

import jaxdmd
from jaxdmd.data import Dataset
from jaxdmd.pipeline import DiscoveryConfig
from jaxdmd.search import SearchConfig


def _recordings(n: int = 3, noise: float = 0.005) -> list[Dataset]:
    """d a/dt = 50 (w - 1), d w/dt = 0.02 u - 0.5 (w - 1), u measured, stepping at t = 1 s."""
    t = np.linspace(0.0, 6.0, 601)
    out = []
    for k in range(n):
        rng = np.random.default_rng(10 + k)
        u = np.where(t < 1.0, 0.0, 1.0 + 0.4 * k) * np.cos(1.3 * t)
        w, a = np.ones_like(t), np.full_like(t, 0.2)
        for i in range(t.size - 1):  # fine explicit Euler sub-steps: the truth
            h = (t[i + 1] - t[i]) / 20
            wi, ai = w[i], a[i]
            for _ in range(20):
                ai, wi = ai + h * 50 * (wi - 1), wi + h * (0.02 * u[i] - 0.5 * (wi - 1))
            w[i + 1], a[i + 1] = wi, ai
        clean = {"a": a, "w": w}
        noisy = {s: x + noise * np.ptp(x) * rng.normal(size=t.shape) for s, x in clean.items()}
        roles = {"a": "state", "w": "state", "u": "input"}
        out.append(Dataset.create(t, {**noisy, "u": u}, roles, events=(1.0,), label=f"rec{k}"))
    return out


SMALL = DiscoveryConfig(
    search=SearchConfig(n_islands=3, prompts_per_round=2, samples_per_prompt=3, max_rounds=6)
)


@pytest.fixture(scope="module")
def found():
    train = _recordings()
    return jaxdmd.discover(train, train[-1:], SMALL, key=jax.random.key(0)), train


def test_discover_is_a_library_call(found):
    result, _ = found
    eqs = result.de.readable()
    assert "u" in eqs["dw/dt"] and "w" in eqs["da/dt"]
    assert "u" not in eqs["da/dt"]  # the hidden effect sits in the right equation
    assert result.report["de"]["rounds"] >= 1
    assert result.ae is None and "ae_skipped" in result.report  # nothing algebraic to close


def test_saved_model_loads_and_simulates_the_same(found, tmp_path):
    result, train = found
    result.save(tmp_path)
    assert (tmp_path / "model.py").exists() and (tmp_path / "summary.json").exists()
    loaded = jaxdmd.load(tmp_path)
    assert loaded.de.source == result.de.source
    assert loaded.de.params == result.de.params
    a = result.simulate(train[0], mode="de")
    b = loaded.simulate(train[0], mode="de")
    assert not a.diverged
    np.testing.assert_allclose(a["a"], b["a"], rtol=0, atol=0)
    score = loaded.score(train, mode="de")
    assert score["n_diverged"] == 0 and score["mean"]["r2"] > 0.9


def test_the_discovered_models_modes_are_reported(found, tmp_path):
    """The data's d w/dt = 0.02 u - 0.5 (w - 1) and d a/dt = 50 (w - 1): linearised, the
    eigenvalues -0.5 and 0 (a is an integrator), at each recording's operating point."""
    result, train = found
    modes = result.report["modes"]
    assert [m["recording"] for m in modes] == [ds.label for ds in train]
    for m in modes:
        real = sorted(e[0] for e in m["eigenvalues"])
        assert real[0] == pytest.approx(-0.5, rel=0.1) and abs(real[1]) < 0.02, real
        assert m["oscillatory"] == []
    result.save(tmp_path)
    assert (
        "## Small-signal modes at the recorded operating points"
        in (tmp_path / "equations.md").read_text()
    )


def test_load_refuses_what_is_not_a_model(tmp_path):
    with pytest.raises(ValueError, match="does not exist"):
        jaxdmd.load(tmp_path / "nothing")
    (tmp_path / "model.py").write_text("import os\nos.system('echo hi')\n")
    with pytest.raises(ValueError, match="DE_PARAMS"):
        jaxdmd.load(tmp_path)
    bad = (
        "def equation(a, p):\n    return __import__('os')\n\n"
        "DE_PARAMS = [1.0]\nDE_TARGETS = ['a']\n"
    )
    (tmp_path / "model.py").write_text(bad)
    with pytest.raises(ValueError):
        jaxdmd.load(tmp_path)


def test_config_says_what_is_wrong():
    with pytest.raises(ValueError, match="derivatives"):
        DiscoveryConfig(derivatives="exact")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="refit_window"):
        DiscoveryConfig(refit_window=-1.0)
    weighted = DiscoveryConfig()
    assert weighted.de_search().gamma == pytest.approx(weighted.search.gamma / 10)
    plain = dataclasses.replace(weighted, weighted=False)
    assert plain.de_search().gamma == plain.search.gamma


def test_the_structure_does_not_hang_on_the_last_bits(found):
    """A relative perturbation of 1e-12 in every measured value gives the same structure."""
    result, train = found
    rng = np.random.default_rng(7)

    def nudge(x) -> np.ndarray:
        x = np.asarray(x)
        return x * (1 + 1e-12 * rng.standard_normal(x.shape))

    nudged = [ds.with_values({n: nudge(ds[n]) for n in ds.names}) for ds in train]
    again = jaxdmd.discover(nudged, nudged[-1:], SMALL, key=jax.random.key(0))
    assert again.de.source == result.de.source


def _dae_recordings(n: int = 3, noise: float = 0.005) -> list[Dataset]:
    """d a/dt = 50 (w - 1), d w/dt = -0.5 (w - 1) + 0.04 y with y = 0.7 a - 0.3 u measured
    (algebraic: the AE loop closes it), u measured, stepping at t = 1 s."""
    t = np.linspace(0.0, 6.0, 601)
    out = []
    for k in range(n):
        rng = np.random.default_rng(20 + k)
        u = np.where(t < 1.0, 0.0, 1.0 + 0.4 * k) * np.cos(1.3 * t)
        w, a = np.ones_like(t), np.full_like(t, 0.2 - 0.1 * k)
        for i in range(t.size - 1):
            h = (t[i + 1] - t[i]) / 20
            wi, ai = w[i], a[i]
            for _ in range(20):
                y = 0.7 * ai - 0.3 * u[i]
                ai, wi = ai + h * 50 * (wi - 1), wi + h * (-0.5 * (wi - 1) + 0.04 * y)
            w[i + 1], a[i + 1] = wi, ai
        clean = {"a": a, "w": w, "y": 0.7 * a - 0.3 * u}
        noisy = {s: x + noise * np.ptp(x) * rng.normal(size=t.shape) for s, x in clean.items()}
        roles = {"a": "state", "w": "state", "y": "algebraic", "u": "input"}
        out.append(Dataset.create(t, {**noisy, "u": u}, roles, events=(1.0,), label=f"dae{k}"))
    return out


def test_the_algebraic_structure_does_not_hang_on_the_last_bits():
    """With an AE loop: the same perturbation of 1e-12 gives the same state and algebraic
    equations, and the hidden algebraic effect (y from a and u) is found."""
    train = _dae_recordings()
    rng = np.random.default_rng(8)
    nudged = [
        ds.with_values(
            {
                n: np.asarray(ds[n]) * (1 + 1e-12 * rng.standard_normal(ds.n_samples))
                for n in ds.names
            }
        )
        for ds in train
    ]
    first = jaxdmd.discover(train, train[-1:], SMALL, key=jax.random.key(1))
    again = jaxdmd.discover(nudged, nudged[-1:], SMALL, key=jax.random.key(1))
    assert first.ae is not None and "y" in first.ae.contract.targets
    assert set(first.ae.readable()["y"].replace("+", " ").split()) >= {"a", "u"}
    assert again.de.source == first.de.source and again.ae.source == first.ae.source
