"""Numerical differentiation: exactness, event splitting, and accuracy under 1 % noise."""

import numpy as np
import pytest

import jaxdmd  # noqa: F401
from jaxdmd.data import DataError, differentiate, differentiation_error, segments

T = np.round(np.arange(0.0, 10.0 + 1e-9, 0.01), 12)


def test_segments_split_at_events():
    segs = segments(T, (1.0, 1.1))
    assert [(s.start, s.stop) for s in segs] == [(0, 100), (100, 110), (110, T.size)]
    assert len(segments(T, (-1.0, 20.0))) == 1  # events outside the record are ignored


@pytest.mark.parametrize("method", ["savgol", "adaptive"])
def test_piecewise_cubic_is_exact(method):
    """Local cubics reproduce a continuous piecewise cubic with kinks at the events exactly."""
    s1, s2 = np.maximum(T - 1.0, 0), np.maximum(T - 1.1, 0)
    x = 0.3 + 2.0 * s1 - 3.0 * s1**2 + 0.5 * s1**3 - 4.0 * s2 + 1.5 * s2**2
    dx = 2.0 * (T >= 1.0) - 6.0 * s1 + 1.5 * s1**2 - 4.0 * (T >= 1.1) + 3.0 * s2
    xs, dxs = differentiate(T, x, events=(1.0, 1.1), method=method)
    np.testing.assert_allclose(xs, x, atol=1e-9)
    np.testing.assert_allclose(dxs, dx, atol=1e-7)
    # without the split the kinks are smeared
    _, blurred = differentiate(T, x, events=(1.0, 1.1), method=method, split=False)
    assert np.abs(blurred - dx).max() > 1.0


def test_shapes_and_methods():
    x = np.stack([np.sin(T), np.cos(T)], axis=1)
    for method in ("savgol", "adaptive", "spline", "gradient"):
        xs, dx = differentiate(T[:300], x[:300], events=(1.0,), method=method)
        assert xs.shape == dx.shape == (300, 2)
        # the natural smoothing spline is biased at segment ends (zero curvature there)
        atol = 2e-2 if method == "spline" else 1e-3
        np.testing.assert_allclose(dx[:, 0], np.cos(T[:300]), atol=atol)
    xs, dx = differentiate(T, np.sin(T))
    assert xs.shape == dx.shape == T.shape
    with pytest.raises(DataError, match="unknown method"):
        differentiate(T, np.sin(T), method="magic")
    with pytest.raises(DataError, match="strictly increasing"):
        differentiate(T[::-1], np.sin(T))


def test_lone_sample_between_events():
    _, dx = differentiate(T[:50], 2.0 * T[:50], events=(0.2, 0.21))
    assert np.all(np.isfinite(dx))
    np.testing.assert_allclose(dx, 2.0, atol=1e-9)


def test_accuracy_under_one_percent_noise():
    """Relative RMS error of dx/dt on the benchmark-like synthetic signals.

    Measured (docs/data.md, 200 signals): median 0.079, 90th percentile 0.14 for the default;
    finite differences give 0.80 and the same smoother without the event split 0.23.
    The threshold 0.12 on the median of 30 signals leaves room for sampling variation while
    still failing if the split or the adaptive window is lost.
    """
    r = differentiation_error(n_signals=30, seed=123)
    assert r["deriv_median"] < 0.12
    assert r["value_median"] < 0.03  # smoothed x: error below the 1 %-of-range noise
    unsplit = differentiation_error(n_signals=30, seed=123, split=False)
    assert unsplit["deriv_median"] > 1.5 * r["deriv_median"]
    raw = differentiation_error("gradient", n_signals=30, seed=123)
    assert raw["deriv_median"] > 0.5


def test_matched_filter_reproduces_the_estimator_on_a_fast_transient():
    """D x = S dx/dt: the estimate equals the matched smoothing of the exact derivative."""
    from jaxdmd.data import matched_filter

    t = np.arange(0.0, 3.0 + 1e-9, 0.01)
    events = (1.0, 1.1)
    tau = 0.04  # as fast as e''_d after a fault
    x = np.where(t < 1.0, np.sin(t), np.sin(1.0) + 0.5 * (1 - np.exp(-(t - 1.0) / tau)))
    dxdt = np.where(t < 1.0, np.cos(t), 0.5 / tau * np.exp(-(t - 1.0) / tau))
    _, estimate = differentiate(t, x, events=events)
    index, weight = matched_filter(t, events=events)
    matched = np.sum(dxdt[index] * weight, axis=1)
    plain_error = np.abs(estimate - dxdt).max()
    matched_error = np.abs(estimate - matched).max()
    assert index.shape == weight.shape and index.shape[0] == len(t)
    assert index.shape[1] < 40  # a band, not a dense matrix
    # only the trapezoid rule on the 0.04 s exponential remains: ten times closer
    assert matched_error < 0.15 * plain_error


def _dense_matched_filter(t, events=(), method="adaptive", **kw):
    """The matched filter as it was built before the band construction (issue #15): the dense
    derivative matrix from `differentiate` of the identity, O(n^2) memory."""
    t = np.asarray(t, dtype=np.float64)
    n = len(t)
    _, d = differentiate(t, np.eye(n), events=events, method=method, **kw)
    c = np.cumsum(d[:, ::-1], axis=1)[:, ::-1]
    w = c[:, 1:] * np.diff(t)
    s = np.zeros_like(d)
    s[:, :-1] += w / 2
    s[:, 1:] += w / 2
    s[np.abs(s) < 1e-10 * np.abs(s).max()] = 0.0
    nonzero = s != 0
    lo = np.where(nonzero.any(axis=1), nonzero.argmax(axis=1), 0)
    hi = np.where(nonzero.any(axis=1), n - 1 - nonzero[:, ::-1].argmax(axis=1), 0)
    width = int((hi - lo).max()) + 1
    index = np.minimum(lo[:, None] + np.arange(width)[None, :], n - 1)
    inside = lo[:, None] + np.arange(width)[None, :] <= hi[:, None]
    weight = np.where(inside, np.take_along_axis(s, index, axis=1), 0.0)
    return index, weight


def _grids():
    rng = np.random.default_rng(7)
    for n in (5, 7, 12, 61, 300, 600):
        t = np.round(np.arange(n) * 0.01, 12)
        jitter = np.cumsum(rng.uniform(0.005, 0.015, n))
        yield t, ()
        yield t, (t[n // 3], t[n // 3] + 0.1)  # fault on, cleared 0.1 s later
        yield t, (t[n // 3], t[n // 3 + 1])  # a lone sample between two events
        yield t, (t[1], t[2], t[n - 1])  # events at the ends
        yield jitter, (jitter[n // 2] + 1e-3,)  # a non-uniform grid, an event between samples


@pytest.mark.parametrize("method", ["adaptive", "savgol", "gradient"])
def test_matched_filter_band_equals_the_dense_construction(method):
    """The band construction gives the dense one's index and weight arrays to round-off."""
    from jaxdmd.data import matched_filter

    for t, events in _grids():
        index, weight = matched_filter(t, events=events, method=method)
        ref_index, ref_weight = _dense_matched_filter(t, events, method)
        assert index.shape == ref_index.shape, (len(t), events)
        np.testing.assert_array_equal(index, ref_index)
        scale = np.abs(ref_weight).max()
        np.testing.assert_allclose(weight, ref_weight, rtol=0, atol=1e-12 * scale)


def test_matched_filter_band_with_other_windows():
    """Finer grids and other windows (wider bands, growth) match the dense construction too."""
    from jaxdmd.data import matched_filter

    for dt, kw in ((0.001, {"window": 0.05, "window_min": 0.02}), (0.02, {"growth": 2.0})):
        t = np.arange(400) * dt
        events = (t[150] + dt / 3, t[190])
        index, weight = matched_filter(t, events=events, **kw)
        ref_index, ref_weight = _dense_matched_filter(t, events, **kw)
        np.testing.assert_array_equal(index, ref_index)
        np.testing.assert_allclose(
            weight, ref_weight, rtol=0, atol=1e-12 * np.abs(ref_weight).max()
        )


def test_estimator_band_equals_the_dense_matrices():
    """`estimator_band` holds the matrices of `differentiate` (values and derivatives)."""
    from jaxdmd.data import estimator_band

    for method in ("adaptive", "gradient"):
        for t, events in _grids():
            n = len(t)
            smooth, deriv = differentiate(t, np.eye(n), events=events, method=method)
            lo, s_band, d_band = estimator_band(t, events=events, method=method)
            cols = lo[:, None] + np.arange(s_band.shape[1])[None, :]
            for band, dense in ((s_band, smooth), (d_band, deriv)):
                rebuilt = np.zeros((n, n + band.shape[1]))
                np.put_along_axis(rebuilt, cols, band, axis=1)
                assert np.all(band[cols >= n] == 0)
                scale = np.abs(dense).max()
                np.testing.assert_allclose(rebuilt[:, :n], dense, rtol=0, atol=1e-12 * scale)


def test_matched_filter_of_a_long_recording_is_a_narrow_band():
    """20,000 samples (the dense construction needed 3.2 GB for its n x n matrix alone): the
    band construction returns [n, w] arrays with w set by the estimator's window."""
    from jaxdmd.data import matched_filter

    t = np.arange(20_000) * 0.001
    index, weight = matched_filter(t, events=(1.0, 1.1))
    assert index.shape == weight.shape
    assert index.shape[0] == 20_000 and index.shape[1] <= 2 * round(0.5 * 0.31 / 0.001) + 2
    assert np.all(np.isfinite(weight))
    # the matched operator applied to a constant derivative gives the constant (rows sum to 1)
    assert np.allclose(weight.sum(axis=1)[5:-5], 1.0, atol=1e-6)


def test_estimator_gains_equal_the_dense_columns():
    """`jaxdmd.problems.estimator_gains` from the bands equals the former construction (the
    matrices of `differentiate` from unit samples, a block of columns at a time) to the last
    bit: the noise weights of the default fit, and with them the discovery, are unchanged."""
    from jaxdmd.data import Dataset
    from jaxdmd.problems import estimator_gains

    t = np.round(np.arange(0.0, 6.0, 0.01), 12)
    x = np.sin(t)
    for events in ((), (1.0, 1.1), (1.0, 1.01), (0.01, 5.99)):
        ds = Dataset.create(t, [("x", x)], {"x": "state"}, events=events)
        n, block = len(t), 250
        gains = estimator_gains(ds, block=block)
        diagonal, s_square, d_square = np.zeros(n), np.zeros(n), np.zeros(n)
        for start in range(0, n, block):
            cols = np.arange(start, min(n, start + block))
            unit = np.zeros((n, cols.size))
            unit[cols, np.arange(cols.size)] = 1.0
            s_cols, d_cols = differentiate(t, unit, events=events)
            diagonal[cols] = s_cols[cols, np.arange(cols.size)]
            s_square += np.sum(s_cols**2, axis=1)
            d_square += np.sum(d_cols**2, axis=1)
        np.testing.assert_array_equal(gains.smoother_diagonal, diagonal)
        np.testing.assert_array_equal(gains.smoother_square, s_square)
        np.testing.assert_array_equal(gains.derivative_square, d_square)


def test_matched_filter_of_the_benchmark_grid_is_the_dense_one_to_the_last_bit():
    """On the benchmark's grid (10 s at 0.01 s, fault at 1.0 s, cleared at 1.1 s) the band
    construction gives the dense construction's weights exactly (the same local fits, sums in
    the same order), so a discovery on the benchmark is unchanged by it."""
    from jaxdmd.data import matched_filter

    t = np.round(np.arange(0.0, 10.0 + 1e-9, 0.01), 12)
    for events in ((1.0, 1.1), (1.0, 1.01)):  # the second leaves a lone sample between them
        index, weight = matched_filter(t, events=events)
        ref_index, ref_weight = _dense_matched_filter(t, events)
        np.testing.assert_array_equal(index, ref_index)
        np.testing.assert_array_equal(weight, ref_weight)
