"""Hypothesis-generated bad tables always raise DataError naming the right column."""

import json

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import jaxdmd  # noqa: F401
from jaxdmd.data import ROLES, DataError, Dataset
from jaxdmd.whitelist import invalid_variable_name

# valid channel names: identifiers a skeleton can use (not p, sin, jnp, keywords ...)
NAMES = st.from_regex(r"[A-Za-z][A-Za-z0-9_]{0,7}", fullmatch=True).filter(
    lambda s: s.lower() not in ("t", "time", "time_s", "t_s") and invalid_variable_name(s) is None
)


@st.composite
def tables(draw):
    """A valid table: t, channels (name -> column) and roles."""
    n = draw(st.integers(8, 40))
    names = draw(st.lists(NAMES, min_size=1, max_size=6, unique=True))
    t = np.cumsum(draw(st.lists(st.floats(0.001, 0.1), min_size=n, max_size=n)))
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    channels = {nm: rng.normal(size=n) for nm in names}
    roles = {nm: draw(st.sampled_from(ROLES)) for nm in names}
    return t, channels, roles


def expect(name, fn):
    """fn() raises DataError and only DataError, and the message names the column."""
    try:
        fn()
    except DataError as err:
        assert repr(name) in str(err), (name, str(err))
    else:
        raise AssertionError(f"no DataError for a bad column {name!r}")


def csv_roundtrip(tmp_path, t, header, columns, roles):
    """Write a CSV table (+ sidecar) and load it."""
    path = tmp_path / "bad.csv"
    rows = zip(t, *columns, strict=True)
    lines = [",".join(["t", *header])] + [",".join(repr(float(v)) for v in r) for r in rows]
    path.write_text("\n".join(lines) + "\n")
    (tmp_path / "bad.csv.json").write_text(json.dumps({"roles": roles}))
    return Dataset.load(path)


SETTINGS = settings(
    max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)


@SETTINGS
@given(table=tables(), data=st.data())
def test_nan_or_inf_anywhere(table, data, tmp_path):
    t, channels, roles = table
    cols = ["t", *channels]
    target = data.draw(st.sampled_from(cols))
    row = data.draw(st.integers(0, len(t) - 1))
    value = data.draw(st.sampled_from([np.nan, np.inf, -np.inf]))
    t, channels = t.copy(), {k: v.copy() for k, v in channels.items()}
    (t if target == "t" else channels[target])[row] = value
    expect(target, lambda: Dataset.create(t, channels, roles))
    expect(target, lambda: csv_roundtrip(tmp_path, t, list(channels), channels.values(), roles))


@SETTINGS
@given(table=tables(), data=st.data())
def test_shuffled_or_repeated_time(table, data, tmp_path):
    t, channels, roles = table
    n = len(t)
    if data.draw(st.booleans()):
        perm = data.draw(st.permutations(range(n)).filter(lambda p: list(p) != sorted(p)))
        t = t[list(perm)]
    else:
        i = data.draw(st.integers(1, n - 1))
        j = data.draw(st.integers(0, i - 1))
        t = t.copy()
        t[i] = t[j]
    expect("t", lambda: Dataset.create(t, channels, roles))
    expect("t", lambda: csv_roundtrip(tmp_path, t, list(channels), channels.values(), roles))


@SETTINGS
@given(table=tables(), data=st.data())
def test_duplicate_names(table, data, tmp_path):
    t, channels, roles = table
    pairs = list(channels.items())
    dup = data.draw(st.sampled_from(pairs))
    at = data.draw(st.integers(0, len(pairs)))
    pairs.insert(at, dup)
    name = dup[0]
    expect(name, lambda: Dataset.create(t, pairs, roles))
    header, columns = [p[0] for p in pairs], [p[1] for p in pairs]
    expect(name, lambda: csv_roundtrip(tmp_path, t, header, columns, roles))


@SETTINGS
@given(table=tables(), data=st.data())
def test_unequal_lengths(table, data):
    t, channels, roles = table
    target = data.draw(st.sampled_from(list(channels)))
    delta = data.draw(st.integers(-len(t), 5).filter(lambda d: d != 0))
    col = channels[target]
    channels = dict(channels)
    channels[target] = col[:delta] if delta < 0 else np.concatenate([col, np.zeros(delta)])
    expect(target, lambda: Dataset.create(t, channels, roles))


@SETTINGS
@given(table=tables(), data=st.data())
def test_partial_derivatives_or_bad_role(table, data):
    t, channels, roles = table
    states = [k for k, r in roles.items() if r == "state"]
    if len(states) >= 2:
        given_ = data.draw(st.lists(st.sampled_from(states), unique=True, max_size=len(states) - 1))
        missing = next(s for s in states if s not in given_)
        ders = {s: np.zeros_like(t) for s in given_}
        if given_:
            expect(missing, lambda: Dataset.create(t, channels, roles, derivatives=ders))
    target = data.draw(st.sampled_from(list(channels)))
    bad_role = data.draw(st.text(min_size=1, max_size=8).filter(lambda r: r not in ROLES))
    expect(target, lambda: Dataset.create(t, channels, roles | {target: bad_role}))


@SETTINGS
@given(table=tables())
def test_valid_tables_load(table, tmp_path):
    t, channels, roles = table
    ds = Dataset.create(t, channels, roles)
    back = csv_roundtrip(tmp_path, t, list(channels), channels.values(), roles)
    np.testing.assert_array_equal(back.values, ds.values)
    np.testing.assert_array_equal(back.t, ds.t)
