"""Dataset: construction, access, helpers, I/O round trips and the named errors of bad input."""

import json

import jax
import numpy as np
import pytest

import jaxdmd  # noqa: F401  (enables float64)
from jaxdmd.data import ROLES, DataError, Dataset, stack_samples

T = np.round(np.arange(0.0, 3.0 + 1e-9, 0.01), 12)
ROLE = {"delta": "state", "omega": "state", "P_e": "algebraic", "P_m": "input", "V": "boundary"}
UNITS = {"delta": "rad", "omega": "pu", "P_e": "pu", "P_m": "pu", "V": "pu"}


def channels(t=T):
    return {
        "delta": 0.5 + 0.1 * np.sin(2 * t),
        "omega": 1.0 + 0.001 * np.cos(2 * t),
        "P_e": 0.8 + 0.05 * np.cos(3 * t),
        "P_m": np.full_like(t, 0.8),
        "V": 1.0 - 0.02 * (t > 1.0),
    }


def exact_derivatives(t=T):
    return {"delta": 0.2 * np.cos(2 * t), "omega": -0.002 * np.sin(2 * t)}


@pytest.fixture
def ds():
    return Dataset.create(
        T, channels(), ROLE, UNITS, exact_derivatives(), events=(1.0, 1.1), label="gen31"
    )


def assert_same(a: Dataset, b: Dataset):
    np.testing.assert_array_equal(a.t, b.t)
    np.testing.assert_array_equal(a.values, b.values)
    np.testing.assert_array_equal(a.derivatives, b.derivatives)
    assert (a.names, a.roles, a.units, a.events, a.label) == (
        b.names,
        b.roles,
        b.units,
        b.events,
        b.label,
    )


# -- construction and access ---------------------------------------------------------------------


def test_create_and_access(ds):
    assert ds.names == tuple(ROLE)
    assert ds.state_names == ("delta", "omega")
    assert ds.algebraic_names == ("P_e",)
    assert ds.input_names == ("P_m",)
    assert ds.boundary_names == ("V",)
    assert ds.role("V") == "boundary" and ds.unit("delta") == "rad"
    assert ds.values.dtype == np.float64 and ds.values.shape == (T.size, 5)
    assert ds.derivatives.shape == (T.size, 2)
    np.testing.assert_array_equal(ds["omega"], channels()["omega"])
    np.testing.assert_array_equal(ds.derivative("delta"), exact_derivatives()["delta"])
    assert "V" in ds and "x" not in ds
    assert ds.events == (1.0, 1.1)


def test_is_a_pytree(ds):
    leaves = jax.tree_util.tree_leaves(ds)
    assert len(leaves) == 3
    total = jax.jit(lambda d: d.values.sum() + d.derivatives.sum())(ds)
    assert np.isclose(total, ds.values.sum() + ds.derivatives.sum())
    assert jax.numpy.asarray(ds.t).dtype == np.float64


def test_estimated_derivatives_when_not_given():
    est = Dataset.create(T, channels(), ROLE, events=(1.0, 1.1))
    for s, d in exact_derivatives().items():
        err = np.abs(est.derivative(s) - d).max() / np.abs(d).max()
        assert err < 5e-3, s  # noise-free: only the bias of local cubics over 0.31 s


def test_select_and_with_channels(ds):
    sub = ds.select(["omega", "V"])
    assert sub.names == ("omega", "V") and sub.state_names == ("omega",)
    np.testing.assert_array_equal(sub.derivative("omega"), ds.derivative("omega"))
    more = ds.with_channels({"e_q": 1.0 + 0.1 * T}, {"e_q": "state"}, {"e_q": "pu"})
    assert more.state_names == ("delta", "omega", "e_q")
    np.testing.assert_allclose(more.derivative("e_q"), 0.1, atol=1e-9)
    np.testing.assert_array_equal(more.derivative("delta"), ds.derivative("delta"))
    with pytest.raises(DataError, match="'V'"):
        ds.with_channels({"V": T}, {"V": "boundary"})


def test_window(ds):
    w = ds.window(2.0, 2.5)
    assert w.t[0] == 2.0 and w.t[-1] == 2.5 and w.n_samples == 51
    assert w.events == ()
    np.testing.assert_array_equal(w["delta"], ds["delta"][200:251])
    np.testing.assert_array_equal(w.derivative("omega"), ds.derivative("omega")[200:251])
    assert ds.window(0.5, 1.5).events == (1.0, 1.1)
    with pytest.raises(DataError, match="'t'"):
        ds.window(5.0, 6.0)


def test_with_events(ds):
    moved = ds.with_events([1.05, 0.5, 0.5])  # sorted, duplicates dropped
    assert moved.events == (0.5, 1.05) and ds.events == (1.0, 1.1)
    np.testing.assert_array_equal(moved.values, ds.values)
    # derivatives re-estimated at the new events, as create estimates them (the exact are gone)
    est = Dataset.create(T, channels(), ROLE, UNITS, events=(0.5, 1.05), label="gen31")
    assert_same(moved, est)
    assert ds.select(["V"]).with_events([2.0]).events == (2.0,)  # no states: nothing to estimate
    assert ds.with_events([0.0, 3.0]).events == (0.0, 3.0)  # the span's ends are inside it
    with pytest.raises(DataError, match=r"event at t = 3.5 s is outside .* span \[0.0, 3.0\] s"):
        ds.with_events([1.0, 3.5])
    with pytest.raises(DataError, match="events must be finite"):  # the checks of create
        ds.with_events([float("inf")])
    with pytest.raises(DataError, match="events must be numbers, got 'x'"):
        ds.with_events(["x"])


def test_with_noise(ds):
    noisy = ds.with_noise(jax.random.key(0), level=0.01)
    for name in ds.names:
        diff = noisy[name] - ds[name]
        if ds.role(name) == "state":
            sigma = 0.01 * np.ptp(ds[name])
            assert 0.85 * sigma < diff.std() < 1.15 * sigma, name
        else:
            np.testing.assert_array_equal(diff, 0.0)
    # derivatives re-estimated from the noisy states: close to the exact ones, not equal
    d, d0 = noisy.derivative("delta"), ds.derivative("delta")
    assert not np.array_equal(d, d0)
    assert np.sqrt(np.mean((d - d0) ** 2)) / np.std(d0) < 0.15
    # deterministic in the key; other roles on request; inputs only keep the exact derivatives
    np.testing.assert_array_equal(ds.with_noise(jax.random.key(0)).values, noisy.values)
    inp = ds.with_noise(jax.random.key(1), level=0.02, roles=("boundary",))
    assert np.std(inp["V"] - ds["V"]) > 0
    np.testing.assert_array_equal(inp.derivatives, ds.derivatives)


def test_with_estimated_derivatives_smooth(ds):
    noisy = ds.with_noise(jax.random.key(3))
    smooth = noisy.with_estimated_derivatives(smooth=True)
    err_raw = np.std(noisy["delta"] - ds["delta"])
    err_smooth = np.std(smooth["delta"] - ds["delta"])
    assert err_smooth < 0.6 * err_raw
    np.testing.assert_array_equal(smooth["V"], ds["V"])


def test_stack_samples(ds):
    other = ds.window(0.0, 1.0)
    out = stack_samples([ds, other], ["t", "delta", "d/dt omega"])
    assert set(out) == {"t", "delta", "d/dt omega"}
    assert out["delta"].shape == (T.size + other.n_samples,)
    np.testing.assert_array_equal(out["d/dt omega"][: T.size], ds.derivative("omega"))
    with pytest.raises(DataError, match="'nope'"):
        stack_samples([ds], ["nope"])
    assert ds.samples(["V"])["V"].shape == (T.size,)


# -- I/O ------------------------------------------------------------------------------------------


def test_roundtrip_npz(ds, tmp_path):
    path = ds.save(tmp_path / "run.npz")
    assert_same(Dataset.load(path), ds)


def test_roundtrip_csv(ds, tmp_path):
    path = ds.save(tmp_path / "run.csv")
    assert (tmp_path / "run.csv.json").exists()
    assert_same(Dataset.load(path), ds)
    header = path.read_text().splitlines()[0]
    assert header == "t,delta,omega,P_e,P_m,V,d/dt delta,d/dt omega"


def test_csv_with_stem_sidecar_and_estimated_derivatives(tmp_path):
    path = tmp_path / "meas.csv"
    lines = ["time,delta,V"] + [f"{float(t)!r},{0.1 * float(t) ** 2!r},1.0" for t in T]
    path.write_text("\n".join(lines) + "\n")
    (tmp_path / "meas.json").write_text(
        json.dumps({"roles": {"delta": "state", "V": "boundary"}, "events": [1.0]})
    )
    ds = Dataset.load(path)
    assert ds.names == ("delta", "V") and ds.events == (1.0,) and ds.label == "meas"
    np.testing.assert_allclose(ds.derivative("delta"), 0.2 * T, atol=1e-8)


# -- bad input: each error names the column ----------------------------------------------------


def bad(match, **kw):
    args = {
        "t": T,
        "channels": channels(),
        "roles": ROLE,
        "derivatives": exact_derivatives(),
    } | kw
    with pytest.raises(DataError, match=match):
        Dataset.create(**args)


def test_nan_and_inf_name_column_and_row():
    ch = channels()
    ch["P_e"] = ch["P_e"].copy()
    ch["P_e"][17] = np.nan
    bad(r"'P_e' has NaN at row 17", channels=ch)
    ch = channels()
    ch["V"] = ch["V"].copy()
    ch["V"][3] = np.inf
    bad(r"'V' has an infinite value at row 3", channels=ch)
    d = exact_derivatives()
    d["omega"] = d["omega"].copy()
    d["omega"][5] = np.nan
    bad(r"derivative of column 'omega' has NaN at row 5", derivatives=d)
    t = T.copy()
    t[4] = np.nan
    bad(r"'t' .*NaN at row 4", t=t)


def test_bad_time():
    t = T.copy()
    t[[10, 11]] = t[[11, 10]]
    bad(r"'t'.*decreasing \(unsorted\) at row 11", t=t)
    t = T.copy()
    t[21] = t[20]
    bad(r"'t'.*repeated at row 21", t=t)
    bad(r"'t'.*one-dimensional", t=T[:, None].repeat(2, axis=1))


def test_unequal_lengths():
    ch = channels()
    ch["omega"] = ch["omega"][:-1]
    bad(r"'omega' has 300 samples but t has 301", channels=ch)
    d = exact_derivatives()
    d["delta"] = np.append(d["delta"], 0.0)
    bad(r"'delta' has 302 samples", derivatives=d)


def test_names_and_roles():
    ch = [*channels().items(), ("V", T)]
    bad(r"'V' appears more than once", channels=ch)
    bad(r"'P_m' has no role", roles={k: v for k, v in ROLE.items() if k != "P_m"})
    bad(r"'V' has unknown role 'bounday'", roles=ROLE | {"V": "bounday"})
    bad(r"roles name column 'Q'", roles=ROLE | {"Q": "algebraic"})
    bad(r"units name column 'Q'", units={"Q": "pu"})
    bad(r"'t'.*reserved", channels=channels() | {"t": T})
    bad(r"'d/dt x'.*reserved", channels=channels() | {"d/dt x": T})
    bad(r"non-empty strings", channels=channels() | {"": T})


def test_partial_derivatives():
    bad(r"state column 'omega' has no derivative", derivatives={"delta": T})
    bad(r"column 'V', which is not a state", derivatives=exact_derivatives() | {"V": T})


def test_access_errors(ds):
    with pytest.raises(DataError, match="'x'"):
        ds["x"]
    with pytest.raises(DataError, match="'V' is not a state"):
        ds.derivative("V")
    with pytest.raises(DataError, match="unknown role"):
        ds.names_with_role("states")
    with pytest.raises(DataError):
        Dataset(
            t=T, values=ds.values, derivatives=ds.derivatives[:, :1], names=ds.names,
            roles=ds.roles, units=ds.units,
        )  # fmt: skip


def write_csv(path, header, rows):
    path.write_text("\n".join([",".join(header), *(",".join(map(str, r)) for r in rows)]) + "\n")


def test_csv_errors(tmp_path):
    path = tmp_path / "x.csv"
    side = tmp_path / "x.csv.json"
    side.write_text(json.dumps({"roles": {"a": "state", "b": "input"}}))
    rows = [[0.0, 1.0, 2.0], [0.1, 1.1, 2.0], [0.2, 1.3, 2.0], [0.3, 1.6, 2.0], [0.4, 2.0, 2.0]]

    write_csv(path, ["a", "b", "c"], rows)
    with pytest.raises(DataError, match="no time column"):
        Dataset.load(path)

    write_csv(path, ["t", "a", "b"], rows)
    side.write_text(json.dumps({"roles": {"a": "state", "b": "input", "z": "input"}}))
    with pytest.raises(DataError, match=r"names column 'z', which the CSV .* lacks"):
        Dataset.load(path)
    side.write_text(json.dumps({"roles": {"a": "state"}}))
    with pytest.raises(DataError, match=r"column 'b' .* has no role"):
        Dataset.load(path)
    side.write_text(json.dumps({"roles": {"a": "state", "b": "input"}}))
    assert Dataset.load(path).names == ("a", "b")

    write_csv(path, ["t", "a", "a"], rows)
    with pytest.raises(DataError, match="'a' appears more than once"):
        Dataset.load(path)
    write_csv(path, ["t", "a", "b"], [*rows[:2], [0.2, 1.3]])
    with pytest.raises(DataError, match="column 'b' is missing"):
        Dataset.load(path)
    write_csv(path, ["t", "a", "b"], [*rows[:2], [0.2, "", 2.0]])
    with pytest.raises(DataError, match="column 'a' has an empty cell at row 2"):
        Dataset.load(path)
    write_csv(path, ["t", "a", "b"], [*rows[:2], [0.2, "oops", 2.0]])
    with pytest.raises(DataError, match="column 'a' has non-numeric value 'oops'"):
        Dataset.load(path)
    write_csv(path, ["t", "a", "b", "d/dt b"], [[*r, 0.0] for r in rows])
    with pytest.raises(DataError, match="'b', which is not a state"):
        Dataset.load(path)
    side.unlink()
    write_csv(path, ["t", "a", "b"], rows)
    with pytest.raises(DataError, match="no sidecar"):
        Dataset.load(path)
    assert Dataset.load(path, roles={"a": "state", "b": "input"}).state_names == ("a",)


def test_roles_constant():
    assert ROLES == ("state", "algebraic", "input", "boundary")
