"""Channel roles on the command line: a CSV without a sidecar runs from the command line, and
the flags override or complete a sidecar (issue #15, item 5a)."""

from __future__ import annotations

import json

import numpy as np
import pytest

import jaxdmd  # noqa: F401  (float64)
from jaxdmd.cli_data import load_data, role_flags
from jaxdmd.data import DataError
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
        "--out", str(out),
    ])  # fmt: skip
    assert code == 0, capsys.readouterr().err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["de"]["targets"] == ["x"]
    assert summary["settings"]["states"] == ["x"] and summary["settings"]["boundary"] == ["V"]
    run = json.loads((out / "run.json").read_text())  # --resume reads the data the same way
    assert run["inputs"] == ["u"]


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
