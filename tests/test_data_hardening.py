"""Bad recordings fail when they are loaded, with a message naming the file and the column.

Channel names become variables of the skeletons (they are spliced into code), so they must be
identifiers a skeleton can use; recordings need enough samples for the derivative estimators;
every error of ``Dataset.load`` names the file. Recordings of different lengths and sampling
rates are fitted together: the operators the pipeline builds are checked on such a pair.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import jaxdmd  # noqa: F401  (enables float64)
from jaxdmd.data import (
    MIN_SAMPLES,
    DataError,
    DataFileNotFound,
    Dataset,
    check_compatible,
    load_many,
    synthetic_signal,
)

ROLES = {"delta": "state", "omega": "state", "P_e": "algebraic", "V": "boundary"}


def write_csv(path: Path, header: list[str], n: int = 50, roles: dict | None = None) -> Path:
    t = np.arange(n) * 0.01
    rows = [[ti, *(np.sin(ti + k) for k in range(len(header) - 1))] for ti in t]
    lines = [",".join(header)] + [",".join(repr(float(v)) for v in row) for row in rows]
    path.write_text("\n".join(lines) + "\n")
    if roles is None:
        roles = dict.fromkeys(header[1:], "boundary") | {header[1]: "state"}
    path.with_name(path.name + ".json").write_text(json.dumps({"roles": roles}))
    return path


# -- item 2: channel names ------------------------------------------------------------------------

BAD_NAMES = ["V x", "a-b", "p", "sin", "jnp", "np", "pi", "atan2", "__class__", "_x", "1a",
             "lambda", "None", "delta\u00e9"]  # fmt: skip


@pytest.mark.parametrize("name", BAD_NAMES)
def test_bad_channel_names_are_rejected_on_construction(name):
    t = np.arange(20) * 0.01
    with pytest.raises(DataError, match="cannot be a model variable") as info:
        Dataset.create(
            t, {"delta": np.sin(t), name: np.cos(t)}, {"delta": "state", name: "boundary"}
        )
    assert repr(name) in str(info.value)


@pytest.mark.parametrize("name", ["V x", "p", "sin", "__class__", "a-b"])
def test_bad_channel_names_in_a_csv_name_the_file_and_column(tmp_path, name):
    path = write_csv(tmp_path / "rec.csv", ["t", "delta", name])
    with pytest.raises(DataError) as info:
        Dataset.load(path)
    message = str(info.value)
    assert str(path) in message and repr(name) in message and "model variable" in message


def test_bad_channel_names_in_an_npz_name_the_file_and_column(tmp_path):
    t = np.arange(20) * 0.01
    ds = Dataset.create(
        t, {"delta": np.sin(t), "V": np.cos(t)}, {"delta": "state", "V": "boundary"}
    )
    path = ds.save(tmp_path / "rec.npz")
    with np.load(path) as z:
        arrays = dict(z)
    meta = json.loads(str(arrays["meta"]))
    meta["names"] = ["delta", "V x"]
    meta["roles"] = {"delta": "state", "V x": "boundary"}
    arrays["meta"] = np.array(json.dumps(meta))
    np.savez(path, **arrays)
    with pytest.raises(DataError, match=r"rec\.npz: column 'V x' cannot be a model variable"):
        Dataset.load(path)


def test_valid_names_still_load(tmp_path):
    path = write_csv(tmp_path / "ok.csv", ["t", "delta", "V_t", "theta", "P_e2", "e", "match"])
    assert Dataset.load(path).names == ("delta", "V_t", "theta", "P_e2", "e", "match")


def test_a_bad_name_never_reaches_the_offline_proposer(tmp_path):
    """The report's crash: a column 'V x' gave ``SyntaxError: (V x - 1)`` in proposers/offline.py
    mid-run; now it stops at loading, as a clear error of the command line."""
    path = write_csv(tmp_path / "gen.csv", ["t", "delta", "omega", "V x"])
    with pytest.raises(DataError, match=r"gen\.csv: column 'V x' cannot be a model variable"):
        load_many([path])


# -- item 3: too few samples ----------------------------------------------------------------------


@pytest.mark.parametrize("n", [2, 3, MIN_SAMPLES - 1])
def test_too_short_recordings_are_rejected_with_the_minimum(tmp_path, n):
    path = write_csv(tmp_path / "short.csv", ["t", "delta", "V"], n=n)
    with pytest.raises(DataError) as info:
        Dataset.load(path)
    message = str(info.value)
    assert str(path) in message
    assert f"at least {MIN_SAMPLES} samples, got {n}" in message
    assert "column 't'" in message


def test_the_minimum_is_enough_for_the_estimators(tmp_path):
    path = write_csv(tmp_path / "five.csv", ["t", "delta", "V"], n=MIN_SAMPLES)
    ds = Dataset.load(path)
    assert ds.n_samples == MIN_SAMPLES
    assert np.all(np.isfinite(ds.derivatives)) and np.ptp(ds.derivatives) > 0
    from jaxdmd.data import matched_filter

    index, weight = matched_filter(ds.t)
    assert np.all(np.isfinite(weight)) and index.shape[0] == MIN_SAMPLES


# -- item 5: messages name the file ---------------------------------------------------------------


def test_missing_file_says_not_found(tmp_path):
    path = tmp_path / "nowhere.csv"
    with pytest.raises(DataFileNotFound, match=r"nowhere\.csv: not found") as info:
        Dataset.load(path)
    assert isinstance(info.value, FileNotFoundError) and isinstance(info.value, DataError)
    with pytest.raises(DataError, match="is a directory"):
        Dataset.load(tmp_path)


def test_nan_in_the_second_of_three_files_names_that_file(tmp_path):
    paths = [write_csv(tmp_path / f"rec{i}.csv", ["t", "delta", "V"]) for i in range(3)]
    text = paths[1].read_text().splitlines()
    cells = text[7].split(",")
    cells[2] = "nan"
    text[7] = ",".join(cells)
    paths[1].write_text("\n".join(text) + "\n")
    with pytest.raises(DataError) as info:
        load_many(paths)
    message = str(info.value)
    assert message.startswith(f"{paths[1]}: ")
    assert "column 'V' has NaN at row 6" in message
    assert str(paths[0]) not in message and str(paths[2]) not in message


@pytest.mark.parametrize(
    ("content", "expected"),
    [
        ("t,delta\n0,1\n0.1,2\n0.1,3\n0.2,4\n0.3,5\n", "(time) must be strictly increasing"),
        ("t,delta\n0,1\n0.1,oops\n", "column 'delta' has non-numeric value 'oops' at row 1"),
        ("t,delta\n0,1\n0.1\n", "column 'delta' is missing"),
    ],
)
def test_every_csv_error_names_the_file(tmp_path, content, expected):
    path = tmp_path / "bad.csv"
    path.write_text(content)
    path.with_name("bad.csv.json").write_text(json.dumps({"roles": {"delta": "state"}}))
    with pytest.raises(DataError) as info:
        Dataset.load(path)
    assert str(path) in str(info.value) and expected in str(info.value)


def test_a_damaged_npz_is_a_data_error_naming_the_file(tmp_path):
    path = tmp_path / "broken.npz"
    path.write_bytes(b"PK\x03\x04 not really a zip")
    with pytest.raises(DataError, match=r"broken\.npz: cannot be read"):
        Dataset.load(path)


# -- item 5: recordings of different lengths and sampling rates -----------------------------------


def recording(dt: float, t_end: float, events: tuple[float, float], seed: int) -> tuple:
    t = np.round(np.arange(0.0, t_end + 1e-9, dt), 12)
    rng = np.random.default_rng(seed)
    x, dx = synthetic_signal(rng, t, events)
    y, dy = synthetic_signal(rng, t, events)
    channels = {"delta": x, "omega": y, "P_e": x * y, "V": 1 + 0.1 * np.cos(t)}
    ds = Dataset.create(t, channels, ROLES, events=events, label=f"dt {dt}")
    return ds, np.stack([dx, dy], axis=1)


def test_recordings_of_different_lengths_and_rates_are_fitted_together():
    from jaxdmd.problems import _groups, _stack, integral_operator, matched_operator

    a, da = recording(0.01, 6.0, (1.0, 1.1), 0)
    b, db = recording(0.025, 4.0, (2.0, 2.15), 1)
    datasets = [a, b]
    check_compatible(datasets)  # lengths, rates and events may differ
    n_a, n_b = a.n_samples, b.n_samples
    assert n_a != n_b and a.dt != b.dt

    stacked = _stack(datasets)
    assert stacked["delta"].shape == (n_a + n_b,)
    np.testing.assert_array_equal(np.asarray(_groups(datasets)), [0] * n_a + [1] * n_b)

    # the matched operator of each recording is its own estimator's: S @ dx/dt = D @ x, block by
    # block, and never mixes samples of the two recordings
    op = matched_operator(datasets)
    index, weight = np.asarray(op.index), np.asarray(op.weight)
    rows_a = index[:n_a][weight[:n_a] != 0]
    rows_b = index[n_a:][weight[n_a:] != 0]
    assert rows_a.max() < n_a <= rows_b.min()
    exact = np.concatenate([da, db])  # [n_a + n_b, 2]
    estimated = np.concatenate([a.derivatives, b.derivatives])
    smoothed = np.stack([np.asarray(op(exact[:, j])) for j in range(2)], axis=1)
    scale = np.abs(estimated).max(axis=0)
    assert np.all(np.abs(smoothed - estimated).max(axis=0) < 0.02 * scale)

    # the integral operator integrates over each recording's own grid, never across the seam
    op, ends = integral_operator(datasets, width=0.2)
    index, weight = np.asarray(op.index), np.asarray(op.weight)
    assert np.all(ends[:n_a] < n_a) and np.all(ends[n_a:] >= n_a)
    x = np.concatenate([a["delta"], b["delta"]])
    integral = np.asarray(op(exact[:, 0]))
    increment = x[ends[:, 1]] - x[ends[:, 0]]
    assert np.abs(integral - increment).max() < 0.02 * np.ptp(x)


def test_check_compatible_names_the_files(tmp_path):
    a = write_csv(tmp_path / "a.csv", ["t", "delta", "V"])
    b = write_csv(tmp_path / "b.csv", ["t", "delta", "theta"])
    with pytest.raises(DataError, match=r"b\.csv: its channels differ from those of .*a\.csv"):
        load_many([a, b])
    c = write_csv(tmp_path / "c.csv", ["t", "delta", "V"], roles={"delta": "state", "V": "input"})
    with pytest.raises(DataError, match=r"c\.csv: column 'V' has the role 'input'"):
        load_many([a, c])
    d = write_csv(tmp_path / "d.csv", ["t", "delta", "V"], n=80)  # longer: compatible
    assert [ds.n_samples for ds in load_many([a, d])] == [50, 80]
