"""COMTRADE recordings (.cfg + .dat) through the optional package ``comtrade`` (issue #15,
item 5)."""

from __future__ import annotations

import json

import numpy as np
import pytest

import jaxdmd  # noqa: F401  (float64)
from jaxdmd.cli_data import load_data
from jaxdmd.data import DataError, Dataset, data_columns, stored_roles
from jaxdmd.run import parse_args

pytest.importorskip("comtrade")

N = 300
RATE = 100.0


def write_comtrade(folder, ids=("x", "u"), stem="rec"):
    """An ASCII COMTRADE 1999 recording at 100 Hz: x = 1 - exp(-(t - 1) / 0.5) after a step
    of u at 1 s (integers scaled by 1e-4), and one status channel."""
    t = np.arange(N) / RATE
    u = (t >= 1.0).astype(float)
    x = np.where(t >= 1.0, 1.0 - np.exp(-(t - 1.0) / 0.5), 0.0)
    units = ("pu", "kV")
    analog = [
        f"{k + 1},{name},,,{units[k]},0.0001,0.0,0,-999999,999999,1,1,P"
        for k, name in enumerate(ids)
    ]
    cfg = [
        "STATION,DEVICE,1999",
        f"{len(ids) + 1},{len(ids)}A,1D",
        *analog,
        f"{len(ids) + 1},trip,,,0",
        "50",
        "1",
        f"{RATE:g},{N}",
        "01/05/2024,12:00:00.000000",
        "01/05/2024,12:00:01.000000",
        "ASCII",
        "1",
    ]
    (folder / f"{stem}.cfg").write_text("\n".join(cfg) + "\n")
    lines = [
        f"{i + 1},{round(i * 1e6 / RATE)},{round(x[i] * 1e4)},{round(u[i] * 1e4)},{int(u[i])}"
        for i in range(N)
    ]
    (folder / f"{stem}.dat").write_text("\n".join(lines) + "\n")
    return folder / f"{stem}.cfg", t, np.round(x * 1e4) * 1e-4


def test_load_comtrade_with_roles_or_a_sidecar(tmp_path):
    cfg, t, x = write_comtrade(tmp_path)
    assert data_columns(cfg) == ["x", "u"]  # the status channel is left out
    ds = Dataset.load(cfg, roles={"x": "state", "u": "input"}, events=(1.0,))
    np.testing.assert_allclose(ds.t, t, atol=1e-12)
    np.testing.assert_allclose(ds["x"], x, atol=1e-12)
    assert ds.units == ("pu", "kV") and ds.state_names == ("x",) and ds.events == (1.0,)
    cfg.with_name("rec.cfg.json").write_text(
        json.dumps({"roles": {"x": "state", "u": "input"}, "events": [1.0]})
    )
    assert stored_roles(cfg) == {"x": "state", "u": "input"}
    assert Dataset.load(cfg).events == (1.0,)


def test_comtrade_with_the_role_flags(tmp_path):
    cfg, _, _ = write_comtrade(tmp_path)
    args = parse_args(["discover", "--data", str(cfg), "--states", "x", "--inputs", "u"])
    (ds,) = load_data([cfg], args)
    assert ds.roles == ("state", "input")
    args = parse_args(["discover", "--data", str(cfg), "--states", "x"])
    with pytest.raises(DataError, match=r"rec.cfg: column 'u' has no role; .*--inputs"):
        load_data([cfg], args)


def test_comtrade_errors_name_the_file_and_the_channel(tmp_path):
    cfg, _, _ = write_comtrade(tmp_path)
    with pytest.raises(DataError, match=r"rec.cfg: no sidecar"):
        Dataset.load(cfg)
    with pytest.raises(DataError, match=r"names column 'z', which the COMTRADE file .* lacks"):
        Dataset.load(cfg, roles={"x": "state", "u": "input", "z": "input"})
    with pytest.raises(DataError, match=r"column 'u' of .*rec.cfg has no role"):
        Dataset.load(cfg, roles={"x": "state"})
    bad, _, _ = write_comtrade(tmp_path, ids=("x", "VA-N"), stem="bad")
    with pytest.raises(DataError, match=r"bad.cfg: column 'VA-N' cannot be a model variable"):
        Dataset.load(bad, roles={"x": "state", "VA-N": "input"})
    (tmp_path / "rec.dat").unlink()
    with pytest.raises(DataError, match=r"rec.cfg: cannot be read as COMTRADE"):
        Dataset.load(cfg, roles={"x": "state", "u": "input"})
