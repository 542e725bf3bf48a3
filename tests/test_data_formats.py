"""Input formats: time headers, ISO-8601 timestamps, tables (pandas or a stand-in), roles read
from the files (issue #15, item 5)."""

from __future__ import annotations

import json

import numpy as np
import pytest

import jaxdmd  # noqa: F401  (float64)
from jaxdmd.data import (
    DataError,
    Dataset,
    data_columns,
    find_time_column,
    parse_times,
    stored_roles,
)

T = np.round(np.arange(0.0, 1.0, 0.1), 10)
A = np.sin(T)
B = np.cos(T)
ROLES = {"a": "state", "b": "input"}


def write(path, header, times, roles=ROLES):
    body = [f"{t},{float(a)!r},{float(b)!r}" for t, a, b in zip(times, A, B, strict=True)]
    lines = [",".join(header), *body]
    path.write_text("\n".join(lines) + "\n")
    if roles is not None:
        path.with_name(path.name + ".json").write_text(json.dumps({"roles": roles}))
    return path


@pytest.mark.parametrize(
    "header", ["t", "time", "Time (s)", "time_s", "Time", "timestamp", "TIME [s]", "T"]
)
def test_common_time_headers(tmp_path, header):
    ds = Dataset.load(write(tmp_path / "x.csv", [header, "a", "b"], [repr(float(v)) for v in T]))
    np.testing.assert_array_equal(ds.t, T)
    assert ds.names == ("a", "b")


def test_time_key_ignores_case_and_units():
    assert find_time_column(["a", "Time (s)", "b"]) == "Time (s)"
    assert find_time_column(["a", "Timestamp"]) == "Timestamp"
    assert find_time_column(["a", "times"]) is None


def test_iso_timestamps_become_seconds_from_the_first_sample(tmp_path):
    base = np.datetime64("2024-05-01T12:00:59.500")
    stamps = [str(base + np.timedelta64(round(v * 1000), "ms")) for v in T]  # over 12:01
    ds = Dataset.load(write(tmp_path / "x.csv", ["timestamp", "a", "b"], stamps))
    np.testing.assert_allclose(ds.t, T, atol=1e-12)
    # a space separator, Z and offsets (converted to UTC)
    zoned = ["2024-05-01 12:00:00Z", "2024-05-01T14:00:00.5+02:00", "2024-05-01T11:00:01-01:00"]
    np.testing.assert_allclose(parse_times(zoned, "t"), [0.0, 0.5, 1.0])
    dates = np.array(["2024-01-01T00:00:00", "2024-01-01T00:00:02"], dtype="datetime64[s]")
    np.testing.assert_allclose(parse_times(dates), [0.0, 2.0])


def test_bad_timestamp_names_file_row_and_column(tmp_path):
    base = np.datetime64("2024-05-01T12:00:00.000")
    stamps = [str(base + np.timedelta64(round(v * 1000), "ms")) for v in T]
    stamps[3] = "2024-05-01 noon"
    path = write(tmp_path / "x.csv", ["Time", "a", "b"], stamps)
    with pytest.raises(DataError) as err:
        Dataset.load(path)
    msg = str(err.value)
    assert str(path) in msg and "'Time'" in msg and "row 3" in msg and "noon" in msg


def test_a_bad_cell_among_seconds_is_named(tmp_path):
    secs = [repr(float(v)) for v in T]
    secs[5] = "oops"
    path = write(tmp_path / "x.csv", ["t", "a", "b"], secs)
    with pytest.raises(DataError, match=r"'t' \(time\) has non-numeric value 'oops' at row 5"):
        Dataset.load(path)


def test_missing_time_column_lists_the_names(tmp_path):
    path = write(tmp_path / "x.csv", ["clock", "a", "b"], [repr(float(v)) for v in T])
    with pytest.raises(DataError, match=r"no time column .*Time \(s\)"):
        Dataset.load(path)


def test_roles_and_columns_of_files(tmp_path):
    secs = [repr(float(v)) for v in T]
    path = write(tmp_path / "x.csv", ["Time (s)", "a", "b"], secs, roles=None)
    assert stored_roles(path) == {}
    assert data_columns(path) == ["a", "b"]
    with pytest.raises(DataError, match="--states"):
        Dataset.load(path)  # no sidecar: the message names the command-line flags too
    ds = Dataset.load(path, roles=ROLES)
    assert stored_roles(ds.save(tmp_path / "y.npz")) == ROLES
    assert data_columns(tmp_path / "y.npz") == ["a", "b"]
    ds.save(tmp_path / "z.csv")
    assert stored_roles(tmp_path / "z.csv") == ROLES
    assert data_columns(tmp_path / "z.csv") == ["a", "b"]  # without t and d/dt a


class Frame:
    """The least a table needs for `Dataset.from_frame`: ``.columns`` and ``[name]``."""

    def __init__(self, columns: dict, index=None):
        self._cols = columns
        self.columns = list(columns)
        if index is not None:
            self.index = index

    def __getitem__(self, name):
        return list(self._cols[name])  # a plain list: any array-like


def test_from_frame_with_a_time_column():
    ds = Dataset.from_frame(Frame({"Time (s)": T, "a": A, "b": B}), roles=ROLES)
    np.testing.assert_array_equal(ds.t, T)
    assert ds.names == ("a", "b") and ds.state_names == ("a",)
    ds = Dataset.from_frame(
        Frame({"clock": T, "a": A, "b": B, "d/dt a": np.cos(T)}),
        roles=ROLES,
        time="clock",
        units={"a": "rad"},
        events=(0.5,),
    )
    np.testing.assert_array_equal(ds.derivative("a"), np.cos(T))
    assert ds.unit("a") == "rad" and ds.events == (0.5,)


def test_from_frame_with_timestamps_or_an_index():
    base = np.datetime64("2024-05-01T12:00:00.000")
    stamps = [str(base + np.timedelta64(round(v * 1000), "ms")) for v in T]
    ds = Dataset.from_frame(Frame({"timestamp": stamps, "a": A, "b": B}), roles=ROLES)
    np.testing.assert_allclose(ds.t, T, atol=1e-12)
    index = base + (T * 1000).round().astype("timedelta64[ms]")  # a datetime64 index
    ds = Dataset.from_frame(Frame({"a": A, "b": B}, index=index), roles=ROLES)
    np.testing.assert_allclose(ds.t, T, atol=1e-12)


def test_from_frame_errors_name_the_column():
    with pytest.raises(DataError, match=r"no time column .* no index"):
        Dataset.from_frame(Frame({"a": A, "b": B}), roles=ROLES)
    with pytest.raises(DataError, match=r"column 'c' of the frame has no role"):
        Dataset.from_frame(Frame({"t": T, "a": A, "b": B, "c": B}), roles=ROLES)
    with pytest.raises(DataError, match=r"roles name column 'z', which the frame lacks"):
        Dataset.from_frame(Frame({"t": T, "a": A, "b": B}), roles={**ROLES, "z": "input"})
    with pytest.raises(DataError, match=r"time='clock' names a column the frame lacks"):
        Dataset.from_frame(Frame({"t": T, "a": A, "b": B}), roles=ROLES, time="clock")
    bad = list(B)
    bad[4] = "oops"
    with pytest.raises(DataError, match=r"column 'b' is not numeric"):
        Dataset.from_frame(Frame({"t": T, "a": A, "b": bad}), roles=ROLES)


def test_from_frame_with_pandas():
    pd = pytest.importorskip("pandas")
    index = pd.date_range("2024-05-01 12:00", periods=len(T), freq="100ms", name="when")
    df = pd.DataFrame({"a": A, "b": B}, index=index)
    ds = Dataset.from_frame(df, roles=ROLES)
    np.testing.assert_allclose(ds.t, T, atol=1e-12)
    df = pd.DataFrame({"Time (s)": T, "a": A, "b": B})
    np.testing.assert_array_equal(Dataset.from_frame(df, roles=ROLES)["b"], B)
    with pytest.raises(DataError, match="row-number index"):
        Dataset.from_frame(pd.DataFrame({"a": A, "b": B}), roles=ROLES)
    zoned = pd.DataFrame({"time": index.tz_localize("Europe/Berlin"), "a": A, "b": B})
    np.testing.assert_allclose(Dataset.from_frame(zoned, roles=ROLES).t, T, atol=1e-12)
