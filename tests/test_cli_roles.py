"""Channel roles on the command line: a CSV without a sidecar runs from the command line, and
the flags override or complete a sidecar (issue #15, item 5a)."""

from __future__ import annotations

import json

import numpy as np
import pytest

import jaxdmd  # noqa: F401  (float64)
from jaxdmd.cli_data import load_data, role_flags
from jaxdmd.cli_diagnose import load_recordings
from jaxdmd.data import DataError, Dataset
from jaxdmd.run import main, parse_args


@pytest.fixture
def csv(tmp_path):
    """dx/dt = (u - x) / 0.5 after a step of u at 1 s; time header 'Time (s)', no sidecar."""
    t = np.round(np.arange(0.0, 3.0, 0.01), 10)
    u = np.where(t >= 1.0, 1.0, 0.0)
    x = np.where(t >= 1.0, 1.0 - np.exp(-(t - 1.0) / 0.5), 0.0)
    v = 1.0 + 0.1 * x
    path = tmp_path / "rec.csv"
    rows = [",".join(repr(float(c)) for c in row) for row in np.column_stack([t, x, u, v])]
    path.write_text("\n".join(["Time (s),x,u,V", *rows]) + "\n")
    return path


def args(*flags: str):
    return parse_args(["discover", "--data", "unused.csv", *flags])


def test_discover_runs_on_a_csv_without_sidecar(csv, tmp_path, capsys):
    out = tmp_path / "out"
    code = main([
        "discover", "--data", str(csv), "--states", "x", "--inputs", "u", "--boundary", "V",
        "--rounds", "1", "--skip-ae", "--prompts", "1", "--samples", "2", "--islands", "1",
        "--events", "1.0", "--out", str(out),
    ])  # fmt: skip
    assert code == 0, capsys.readouterr().err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["de"]["targets"] == ["x"]
    assert summary["settings"]["states"] == ["x"] and summary["settings"]["boundary"] == ["V"]
    run = json.loads((out / "run.json").read_text())  # --resume reads the data the same way
    assert run["inputs"] == ["u"] and run["events"] == "1.0"


def test_flags_give_roles_and_errors_name_file_column_and_flag(csv):
    (ds,) = load_data([csv], args("--states", "x", "--role", "u=input", "--boundary", "V"))
    assert ds.roles == ("state", "input", "boundary") and ds.state_names == ("x",)
    (ds,) = load_data([csv], args("--states", "x,u", "--boundary", "V"))
    assert ds.state_names == ("x", "u")

    with pytest.raises(DataError) as err:
        load_data([csv], args("--states", "x,y", "--inputs", "u"))
    assert str(csv) in str(err.value) and "--states names column 'y'" in str(err.value)
    with pytest.raises(DataError) as err:
        load_data([csv], args("--states", "x", "--inputs", "u"))
    msg = str(err.value)
    assert str(csv) in msg and "column 'V' has no role" in msg and "--boundary V" in msg
    with pytest.raises(DataError, match=r"'x' is given two roles: state \(--states\)"):
        role_flags(args("--states", "x", "--role", "x=input"))
    with pytest.raises(DataError, match="--role 'x:state': expected NAME=ROLE"):
        role_flags(args("--role", "x:state"))
    with pytest.raises(DataError, match="--role 'x=bogus'"):
        role_flags(args("--role", "x=bogus"))


def test_flags_override_and_complete_the_sidecar(csv):
    side = csv.with_name(csv.name + ".json")
    side.write_text(json.dumps({"roles": {"x": "state", "u": "boundary"}}))
    (ds,) = load_data([csv], args("--inputs", "u", "--boundary", "V"))  # override u, add V
    assert dict(zip(ds.names, ds.roles, strict=True)) == {
        "x": "state",
        "u": "input",
        "V": "boundary",
    }
    side.write_text(json.dumps({"roles": {"x": "state", "u": "input", "z": "input"}}))
    with pytest.raises(DataError, match=r"its sidecar names column 'z', which the file lacks"):
        load_data([csv], args("--boundary", "V"))


def test_without_sidecar_or_flags_the_error_names_the_flags(csv, capsys):
    code = main(["discover", "--data", str(csv), "--out", str(csv.parent / "o"), "--skip-ae"])
    err = capsys.readouterr().err
    assert code == 2 and str(csv) in err and "--states" in err and "Traceback" not in err
    assert not (csv.parent / "o").exists()


def test_diagnose_takes_the_role_flags():
    a = parse_args(["diagnose", "--data", "a.csv", "--model", "classical", "--states", "x,y"])
    assert role_flags(a) == {"x": ("state", "--states"), "y": ("state", "--states")}


def test_diagnose_runs_on_a_csv_without_sidecar(csv, tmp_path, capsys):
    model = tmp_path / "lag.py"
    model.write_text("def equation(x, u, p):\n    return (p[0] * x + p[1] * u,)\n")
    out = tmp_path / "report"
    code = main([
        "diagnose", "--data", str(csv), "--model", str(model), "--rounds", "0",
        "--states", "x", "--role", "u=input", "--role", "V=boundary", "--out", str(out),
    ])  # fmt: skip
    assert code == 0, capsys.readouterr().err
    assert (out / "report.md").exists()


def step_error(ds):
    """The largest error of the estimated d/dt x in the 0.1 s after the step of u at 1 s."""
    t = ds.t
    exact = np.where(t >= 1.0, 2.0 * np.exp(-(t - 1.0) / 0.5), 0.0)
    after = (t >= 1.0) & (t < 1.1)
    return np.abs(ds.derivative("x") - exact)[after].max()


ROLE_ARGS = ("--states", "x", "--inputs", "u", "--boundary", "V")


def test_events_flag_splits_the_derivatives_at_the_step(csv, tmp_path):
    (smeared,) = load_data([csv], args(*ROLE_ARGS))
    assert smeared.events == () and step_error(smeared) > 0.5  # of a jump of 2 in d/dt x
    other = tmp_path / "other.csv"
    other.write_text(csv.read_text())
    sharp = load_data([csv, other], args(*ROLE_ARGS, "--events", "1.0"))
    for ds in sharp:  # every file
        assert ds.events == (1.0,) and step_error(ds) < 1e-3
    # the same estimate as giving the events afterwards
    np.testing.assert_array_equal(smeared.with_events([1.0]).derivatives, sharp[0].derivatives)

    # without role flags too (roles from the sidecar, whose events are replaced), and in diagnose
    csv.with_name(csv.name + ".json").write_text(
        json.dumps({"roles": {"x": "state", "u": "input", "V": "boundary"}, "events": [2.0]})
    )
    (ds,) = load_data([csv], args("--events", "1.0"))
    assert ds.events == (1.0,) and step_error(ds) < 1e-3
    a = parse_args(["diagnose", "--data", str(csv), "--model", "classical", "--events", "1.0"])
    (ds,) = load_recordings([str(csv)], a)
    assert ds.events == (1.0,)
    (ds,) = load_data([csv], args("--events", ""))  # '' removes them
    assert ds.events == ()


def test_events_flag_keeps_the_derivatives_a_file_stores(csv):
    rec = Dataset.load(csv, roles={"x": "state", "u": "input", "V": "boundary"})
    given = np.cos(rec.t)  # not an estimate: kept, not re-estimated at the events
    stored = csv.with_name("stored.csv")  # with d/dt x and a sidecar
    Dataset.create(
        rec.t,
        rec.channels(),
        dict(zip(rec.names, rec.roles, strict=True)),
        derivatives={"x": given},
    ).save(stored)
    (ds,) = load_data([stored], args("--events", "0.5,1.0"))
    assert ds.events == (0.5, 1.0)
    np.testing.assert_array_equal(ds.derivative("x"), given)


@pytest.mark.parametrize(
    ("value", "message"),
    [
        ("1.0,abc", "--events '1.0,abc': 'abc' is not a time in seconds"),
        ("1.0,,1.1", "--events '1.0,,1.1': '' is not a time in seconds"),
        ("1.0,nan", "--events '1.0,nan': events must be finite"),
        ("1.0,5", r"--events '1.0,5': event at t = 5.0 s is outside the record's time span "
         r"\[0.0, 2.99\] s"),
    ],
)  # fmt: skip
def test_a_bad_events_flag_names_the_flag_and_the_value(csv, value, message):
    with pytest.raises(DataError, match=message) as err:
        load_data([csv], args(*ROLE_ARGS, "--events", value))
    if "outside" in message:
        assert str(csv) in str(err.value)


def test_time_flag_offers_the_time_as_an_input(csv):
    """``--time``: each recording's time axis joins as an input of unit s (a forcing's argument);
    without it no time channel."""
    from jaxdmd.run import Progress, recordings

    flags = ("--states", "x", "--inputs", "u", "--boundary", "V")
    a = parse_args(["discover", "--data", str(csv), "--test-data", str(csv), *flags, "--time"])
    train, test, _ = recordings(a, Progress())
    for ds in (*train, *test):
        assert ds.role("time") == "input" and ds.unit("time") == "s"
        np.testing.assert_array_equal(np.asarray(ds["time"]), np.asarray(ds.t))
    a = parse_args(["discover", "--data", str(csv), *flags])
    (ds,), _, _ = recordings(a, Progress())
    assert "time" not in ds.names
