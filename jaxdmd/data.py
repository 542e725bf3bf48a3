"""Measured trajectories: the `Dataset` pytree, its I/O and validation, numerical differentiation.

A `Dataset` holds one recording: sample times ``t`` [n], channel values ``values`` [n, c] (one
column per channel) and the time derivatives of the state channels ``derivatives`` [n, s] (exact,
when a simulator provides them, or estimated by `differentiate`). Names, roles, units, the known
discontinuity times (``events``: fault on, fault clear) and a label are static metadata, so a
`Dataset` can be passed through ``jax.jit`` and ``jax.tree_util`` like any equinox Module.

Arrays are stored as numpy float64 (JAX converts them on use). Bad input raises `DataError`, a
``ValueError`` whose message names the offending column (or ``t``) and what is wrong with it.

Numerical differentiation (`differentiate`) splits the record at the events, because the
derivatives of the states jump there, and smooths each segment separately; see ``docs/data.md``
for the measured accuracy of the methods on signals that mimic the benchmark's data.
"""

from __future__ import annotations

import csv
import itertools
import json
import math
import re
import zipfile
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any, Literal

import equinox as eqx
import numpy as np
from numpy.typing import ArrayLike

from jaxdmd.whitelist import invalid_variable_name

__all__ = [
    "COMTRADE_SUFFIXES",
    "DERIVATIVE_PREFIX",
    "METHODS",
    "MIN_SAMPLES",
    "ROLES",
    "DataError",
    "DataFileNotFound",
    "Dataset",
    "check_compatible",
    "data_columns",
    "differentiate",
    "differentiation_error",
    "estimator_band",
    "find_time_column",
    "load_many",
    "matched_filter",
    "parse_times",
    "samples",
    "segments",
    "stack_samples",
    "stored_roles",
    "synthetic_signal",
]

ROLES: tuple[str, ...] = ("state", "algebraic", "input", "boundary")
"""Channel roles: states (with derivatives), algebraic variables, inputs, boundary signals."""

DERIVATIVE_PREFIX = "d/dt "
"""Prefix of derivative columns in CSV files and of derivative names in `stack_samples`."""

Method = Literal["savgol", "adaptive", "spline", "gradient"]
METHODS: tuple[str, ...] = ("savgol", "adaptive", "spline", "gradient")
DEFAULT_METHOD: Method = "adaptive"

MIN_SAMPLES = 5
"""The fewest samples a recording may have: `differentiate` fits local cubics (four
coefficients) and needs a fifth sample to smooth at all (its spline needs five too); with fewer,
the derivative estimates and the fitted scores are meaningless (two samples give a constant
derivative, whose variance of zero makes every normalised error NaN)."""

_TIME_NAMES = ("t", "time", "time_s", "t_s", "timestamp", "seconds")
"""Names of a time column, compared case-insensitively after dropping units in parentheses or
brackets (``Time (s)``, ``TIME [s]``) and turning spaces into ``_`` (`time_key`)."""
_UNITS = re.compile(r"\s*[\(\[][^\)\]]*[\)\]]\s*")
_ISO = re.compile(
    r"^(\d{4}-\d{2}-\d{2}(?:[T ]\d{2}:\d{2}(?::\d{2}(?:[.,]\d+)?)?)?)\s*"
    r"(Z|[+-]\d{2}(?::?\d{2})?)?$"
)
_FORMAT = "jaxdmd.dataset"
_VERSION = 1


class DataError(ValueError):
    """Invalid data: the message names the column (or ``t``) and the problem (and the file, for
    data read by `Dataset.load`)."""


class DataFileNotFound(DataError, FileNotFoundError):
    """`Dataset.load` of a path that does not exist (both a `DataError` and a
    ``FileNotFoundError``)."""


def _in_file(err: DataError, path: Path) -> DataError:
    """``err`` with the file named at the start of its message (if it is not named yet)."""
    message = str(err)
    if str(path) in message:
        return err
    return type(err)(f"{path}: {message}")


# ------------------------------------------------------------------------------------------------
# numerical differentiation
# ------------------------------------------------------------------------------------------------


def segments(t: np.ndarray, events: Iterable[float] = ()) -> list[slice]:
    """Split sample indices at the event times into half-open segments ``[e_k, e_{k+1})``.

    A sample lying on an event (within 1e-6 of the median step) starts the later segment, so the
    derivative reported there is the one right after the event (the post-event one). Events
    outside ``(t[0], t[-1]]`` are ignored.
    """
    t = np.asarray(t, dtype=np.float64)
    n = t.shape[0]
    tol = 1e-6 * float(np.median(np.diff(t))) if n > 1 else 0.0
    cuts = [0]
    for e in sorted(float(e) for e in events):
        i = int(np.searchsorted(t, e - tol, side="left"))
        if cuts[-1] < i < n:
            cuts.append(i)
    cuts.append(n)
    return [slice(a, b) for a, b in itertools.pairwise(cuts)]


def _windows(
    t: np.ndarray, half: np.ndarray, order: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The local fits of `_local_polynomial` on one segment: windows and normal equations.

    Returns ``idx`` [m, wmax] (the window of sample ``i`` is ``idx[i, :width_i]``, contiguous;
    padding repeats its first sample), ``mask`` [m, wmax] (inside the window), the weighted
    Vandermonde matrices ``V`` [m, wmax, order+1] (zero outside the window), the normal matrices
    ``G`` [m, order+1, order+1] and the window time scales ``scale`` [m], and ``start`` [m].
    """
    m = t.shape[0]
    width = np.minimum(2 * half + 1, m)  # [m]
    wmax = int(width.max())
    start = np.clip(np.arange(m) - half, 0, m - width)  # [m]
    idx = start[:, None] + np.arange(wmax)[None, :]  # [m, wmax]
    mask = np.arange(wmax)[None, :] < width[:, None]
    idx = np.where(mask, idx, start[:, None])
    p = np.minimum(order, width - 1)  # [m] degree actually used per sample
    scale = np.maximum(np.ptp(np.where(mask, t[idx], t[start][:, None]), axis=1), 1e-300)
    tau = (t[idx] - t[:, None]) / scale[:, None]  # [m, wmax] in window units
    powers = np.arange(order + 1)
    V = tau[..., None] ** powers  # [m, wmax, order+1]
    V = V * (mask[..., None] & (powers[None, None, :] <= p[:, None, None]))
    # Regularise unused powers (degree > p) to an identity so the normal matrix stays invertible.
    G = np.einsum("mwa,mwb->mab", V, V)
    unused = powers[None, :] > p[:, None]
    G = G + np.einsum("ma,ab->mab", unused.astype(np.float64), np.eye(order + 1))
    return idx, mask, V, G, scale, start


def _local_polynomial(
    t: np.ndarray, x: np.ndarray, half: np.ndarray, order: int
) -> tuple[np.ndarray, np.ndarray]:
    """Local least-squares polynomial (Savitzky-Golay on any grid) on one segment.

    ``half[i]`` is the half-width (in samples) of the window of sample ``i``: the fit uses the
    ``2 half[i] + 1`` samples around ``i``, shifted inwards near the segment ends (as scipy's
    ``savgol_filter(mode="interp")``), and is evaluated at ``t[i]``. Returns the fitted value and
    slope at every sample. ``x`` is [m, k].
    """
    idx, mask, V, G, scale, _ = _windows(t, half, order)
    rhs = np.einsum("mwa,mwk->mak", V, x[idx] * mask[..., None])
    coef = np.linalg.solve(G, rhs)  # [m, order+1, k]
    value = coef[:, 0, :]
    slope = coef[:, 1, :] / scale[:, None] if order >= 1 else np.zeros_like(value)
    return value, slope


def _local_polynomial_band(
    t: np.ndarray, half: np.ndarray, order: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The weights of `_local_polynomial` as band matrices, without applying them to data.

    Returns ``(start, value, slope)``: ``start`` [m] the first sample of each window,
    ``value`` and ``slope`` [m, wmax] the weights of samples ``start[i] + k`` (zero beyond the
    window), so that the fitted value at ``i`` is ``sum_k value[i, k] x[start[i] + k]``. Memory
    is O(m * wmax), not the O(m^2) of applying `_local_polynomial` to the identity.
    """
    _, mask, V, G, scale, start = _windows(t, half, order)
    weights = np.linalg.solve(G, np.swapaxes(V, 1, 2))  # [m, order+1, wmax]
    value = np.where(mask, weights[:, 0, :], 0.0)
    if order >= 1:
        slope = np.where(mask, weights[:, 1, :] / scale[:, None], 0.0)
    else:
        slope = np.zeros_like(value)
    return start, value, slope


def _half_widths(
    t: np.ndarray, window: float, window_min: float | None, growth: float
) -> np.ndarray:
    """Half-widths in samples: fixed ``window``, or growing from ``window_min`` after the start.

    With ``window_min`` set, sample ``i`` of a segment uses the half-width
    ``clip(window_min/2 + growth (t_i - t_0), window_min/2, window/2)`` (in seconds, converted
    with the median step): narrow right after an event, where the fast transients are, wide
    later, where noise dominates.
    """
    dt = float(np.median(np.diff(t))) if t.shape[0] > 1 else 1.0
    h_max = max(1, round(0.5 * window / dt))
    if window_min is None:
        return np.full(t.shape[0], h_max, dtype=np.int64)
    h_min = max(1, round(0.5 * window_min / dt))
    h = 0.5 * window_min / dt + growth * (t - t[0]) / dt
    return np.clip(np.round(h), h_min, h_max).astype(np.int64)


def _spline(t: np.ndarray, x: np.ndarray, lam: float | None) -> tuple[np.ndarray, np.ndarray]:
    """Cubic smoothing spline per column; ``lam=None`` picks the penalty by GCV (scipy)."""
    from scipy.interpolate import make_smoothing_spline

    value = np.empty_like(x)
    slope = np.empty_like(x)
    for j in range(x.shape[1]):
        spl = make_smoothing_spline(t, x[:, j], lam=lam)
        value[:, j] = spl(t)
        slope[:, j] = spl(t, 1)
    return value, slope


def event_samples(t: np.ndarray, events: Sequence[float]) -> np.ndarray:
    """Which samples fall on an event time (to a thousandth of the median step), [n] bool."""
    tol = 1e-3 * float(np.median(np.diff(t))) if t.shape[0] > 1 else 0.0
    hit = np.zeros(t.shape[0], dtype=bool)
    for e in events:
        hit |= np.abs(t - e) <= tol
    return hit


def differentiate(
    t: ArrayLike,
    x: ArrayLike,
    *,
    events: Iterable[float] = (),
    method: Method = DEFAULT_METHOD,
    window: float = 0.31,
    window_min: float = 0.11,
    growth: float = 0.5,
    order: int = 3,
    lam: float | None = None,
    split: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """Smooth ``x`` and estimate ``dx/dt``, piecewise between the ``events``.

    Args:
        t: sample times [n], strictly increasing (any grid).
        x: samples [n] or [n, k] (one column per signal).
        events: known discontinuity times of the derivative (fault on, fault clear). The record
            is split there (see `segments`) and each segment is smoothed on its own, so no
            window straddles a jump of the derivative.
        method: ``"adaptive"`` (default): local cubic fits whose window grows from
            ``window_min`` right after an event to ``window`` (the segment before the first
            event, which starts in steady state, uses ``window`` throughout); ``"savgol"``:
            local polynomial (Savitzky-Golay) fits with a fixed ``window``, shifted inwards at
            the segment ends;
            ``"spline"``: cubic smoothing spline with the penalty ``lam`` (None: chosen by
            generalised cross-validation); ``"gradient"``: second-order finite differences, no
            smoothing.
        window: width of the local fit in seconds (the maximum width for ``"adaptive"``).
        window_min: width right after a segment start for ``"adaptive"``, in seconds.
        growth: how fast the adaptive half-width grows, in seconds per second since the start.
        order: degree of the local polynomials.
        lam: smoothing-spline penalty (``"spline"`` only).
        split: split at the events (True) or smooth the record as one piece (for comparison).

    Returns:
        ``(x_smooth, dxdt)``, both shaped like ``x``: the smoothed samples (use them as
        regressors) and the derivative estimates.

    The defaults were chosen on synthetic signals like the benchmark's (10 s at 0.01 s, transients
    with time constants 0.04-1.5 s starting at the events, Gaussian noise of 1 % of the range);
    see `differentiation_error` and ``docs/data.md``.
    """
    t = np.asarray(t, dtype=np.float64)
    x = np.asarray(x, dtype=np.float64)
    squeeze = x.ndim == 1
    x2 = x[:, None] if squeeze else x
    if t.ndim != 1 or x2.ndim != 2 or x2.shape[0] != t.shape[0]:
        raise DataError(f"differentiate: t has shape {t.shape} but x has shape {x.shape}")
    if t.shape[0] >= 2 and not np.all(np.diff(t) > 0):
        raise DataError("differentiate: t must be strictly increasing")
    if method not in METHODS:
        raise DataError(f"differentiate: unknown method {method!r}; use one of {METHODS}")
    value = np.empty_like(x2)
    slope = np.empty_like(x2)
    for k, seg in enumerate(segments(t, events if split else ())):
        ts, xs = t[seg], x2[seg]
        m = ts.shape[0]
        if m == 1:  # a lone sample between two events: no slope information inside
            value[seg], slope[seg] = xs, np.nan
            continue
        if method == "gradient" or m < 3:
            value[seg] = xs
            slope[seg] = np.gradient(xs, ts, axis=0, edge_order=2 if m >= 3 else 1)
        elif method == "spline" and m >= 5:
            value[seg], slope[seg] = _spline(ts, xs, lam)
        else:
            # Adaptive windows start narrow only where a transient starts: after an event.
            wmin = window_min if method == "adaptive" and k > 0 else None
            half = _half_widths(ts, window, wmin, growth)
            value[seg], slope[seg] = _local_polynomial(ts, xs, half, order)
    # Fill slopes of lone samples from the neighbouring segment start (rare: events 1 step apart).
    bad = np.isnan(slope)
    if bad.any():
        for j in range(slope.shape[1]):
            col = slope[:, j]
            nan = np.isnan(col)
            if (~nan).any():
                col[nan] = np.interp(t[nan], t[~nan], col[~nan])
            else:
                col[nan] = 0.0
    if squeeze:
        return value[:, 0], slope[:, 0]
    return value, slope


# ------------------------------------------------------------------------------------------------
# accuracy measurement on synthetic signals
# ------------------------------------------------------------------------------------------------


def _probe_band(
    apply: Callable[[np.ndarray], np.ndarray], m: int, reach: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The matrices of a linear map ``apply`` (``x`` [m, k] -> ``(value, slope)``, each
    [m, k]) whose rows reach at most ``reach`` samples either side, as bands.

    Impulses ``2 reach + 1`` samples apart do not overlap in the output, so ``2 reach + 1``
    interleaved combs give every entry of the matrices: O(m reach) memory. Returns ``(lo,
    value, slope)`` as `_local_polynomial_band` does.
    """
    period = 2 * reach + 1
    combs = np.zeros((m, period))
    combs[np.arange(m), np.arange(m) % period] = 1.0
    value, slope = apply(combs)
    lo = np.maximum(np.arange(m) - reach, 0)
    cols = lo[:, None] + np.arange(period)[None, :]  # one column of every residue per row
    rows = np.arange(m)[:, None]
    valid = cols < m
    return (
        lo,
        np.where(valid, value[rows, cols % period], 0.0),
        np.where(valid, slope[rows, cols % period], 0.0),
    )


def estimator_band(
    t: ArrayLike,
    *,
    events: Iterable[float] = (),
    method: Method = DEFAULT_METHOD,
    window: float = 0.31,
    window_min: float = 0.11,
    growth: float = 0.5,
    order: int = 3,
    lam: float | None = None,
    split: bool = True,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The matrices of `differentiate` (smoothed values ``S x``, derivatives ``D x``) as bands.

    `differentiate` is linear in ``x`` (for ``"spline"`` only with a fixed ``lam``); this returns
    ``(lo, smooth, deriv)``, ``lo`` [n] and ``smooth``, ``deriv`` [n, w]: ``S[i, lo[i] + k] =
    smooth[i, k]`` (zero where ``lo[i] + k >= n``) and all other entries of row ``i`` zero, the
    same for ``D``. The local fits (``"adaptive"``, ``"savgol"``) are read off their normal
    equations and ``"gradient"`` from probe signals, in O(n w) memory and time; ``"spline"``
    (not local) is the dense segment matrix, O(n^2). Options as for `differentiate`.
    """
    t = np.asarray(t, dtype=np.float64)
    n = t.shape[0]
    if t.ndim != 1:
        raise DataError(f"estimator_band: t has shape {t.shape}")
    if n >= 2 and not np.all(np.diff(t) > 0):
        raise DataError("estimator_band: t must be strictly increasing")
    if method not in METHODS:
        raise DataError(f"estimator_band: unknown method {method!r}; use one of {METHODS}")
    pieces: list[tuple[int, np.ndarray, np.ndarray, np.ndarray]] = []
    lone: list[int] = []
    for k, seg in enumerate(segments(t, events if split else ())):
        ts = t[seg]
        m = ts.shape[0]
        if m == 1:  # a lone sample: its value is kept, its slope interpolated below
            lone.append(seg.start)
            pieces.append((seg.start, np.zeros(1, np.int64), np.ones((1, 1)), np.zeros((1, 1))))
            continue
        if method == "gradient" or m < 3:
            edge = 2 if m >= 3 else 1

            def gradient(x: np.ndarray, ts: np.ndarray = ts, edge: int = edge) -> tuple:
                return x, np.gradient(x, ts, axis=0, edge_order=edge)

            lo, value, slope = _probe_band(gradient, m, 2)
        elif method == "spline" and m >= 5:
            lo = np.zeros(m, dtype=np.int64)
            value, slope = _spline(ts, np.eye(m), lam)
        else:
            wmin = window_min if method == "adaptive" and k > 0 else None
            half = _half_widths(ts, window, wmin, growth)
            lo, value, slope = _local_polynomial_band(ts, half, order)
        pieces.append((seg.start, lo, value, slope))
    width = max(v.shape[1] for _, _, v, _ in pieces)
    lo = np.zeros(n, dtype=np.int64)
    smooth = np.zeros((n, width))
    deriv = np.zeros((n, width))
    for start, lo_k, value, slope in pieces:
        rows = slice(start, start + lo_k.shape[0])
        lo[rows] = lo_k + start
        smooth[rows, : value.shape[1]] = value
        deriv[rows, : slope.shape[1]] = slope
    if lone:  # as differentiate: the slope interpolated in time from the other samples
        good = np.setdiff1d(np.arange(n), lone)
        if good.size:
            gap = int(np.max(np.diff(np.concatenate([[-1], good, [n]]))))
            wide = 2 * width + gap + 1  # rows p and q of the neighbours and the sample itself
            deriv = np.pad(deriv, [(0, 0), (0, wide - width)])
            smooth = np.pad(smooth, [(0, 0), (0, wide - width)])
            for i in lone:
                j = int(np.searchsorted(good, i))
                p, q = good[max(j - 1, 0)], good[min(j, good.size - 1)]
                lo_i = min(lo[p], i)
                row_p, row_q = np.zeros(wide), np.zeros(wide)
                row_p[lo[p] - lo_i : lo[p] - lo_i + width] = deriv[p, :width]
                row_q[lo[q] - lo_i : lo[q] - lo_i + width] = deriv[q, :width]
                # np.interp's own arithmetic, so that the rows are those of differentiate
                if p == q:
                    deriv[i] = row_p
                else:
                    deriv[i] = (row_q - row_p) / (t[q] - t[p]) * (t[i] - t[p]) + row_p
                smooth[i] = 0.0
                smooth[i, i - lo_i] = 1.0  # the lone sample's value is its own
                lo[i] = lo_i
    return lo, smooth, deriv


def matched_filter(
    t: ArrayLike, *, events: Iterable[float] = (), method: Method = DEFAULT_METHOD, **kw: Any
) -> tuple[np.ndarray, np.ndarray]:
    """The smoothing that `differentiate` applies to the true derivative, as a band operator.

    `differentiate` is linear in ``x``: its derivative estimate is ``D @ x`` for a matrix ``D``
    whose rows sum to zero (a constant has no derivative). Hence, exactly,
    ``(D @ x)_i = sum_l c_il (x_l - x_(l-1))`` with ``c_il = sum_(j >= l) D_ij``, and every
    increment is the integral of ``dx/dt`` over its sample interval, approximated by the
    trapezoid rule. So ``D @ x = S @ dxdt`` with a matrix ``S`` that smooths like the estimator.
    Comparing the estimates with ``S @ f(x)`` instead of ``f(x)`` removes the estimator's
    smoothing bias from a fit (fast transients right after the events are where it matters).

    Returns ``(index, weight)``, both ``[n, w]``: ``(S @ y)_i = sum_k weight[i, k] *
    y[index[i, k]]``. Options as for `differentiate` (the same method and windows must be used
    for the derivative estimates the operator is matched to). ``D`` is built as a band
    (`estimator_band`), so memory and time are linear in ``n`` (except for ``"spline"``).
    """
    t = np.asarray(t, dtype=np.float64)
    n = len(t)
    lo, _, d = estimator_band(t, events=events, method=method, **kw)
    b = d.shape[1]
    rows = np.arange(n)[:, None]
    dt = np.diff(t)
    # c[i, lo_i + k] = sum_(j >= lo_i + k) D_ij; left of the band it is the row sum (round-off)
    c = np.cumsum(d[:, ::-1], axis=1)[:, ::-1]  # [n, b]
    # s on the columns lo_i - 1 + r, r = 0..b: s[i, l] = w[i, l] / 2 + w[i, l - 1] / 2 with
    # w[i, l] = c[i, l + 1] dt_l (l <= n - 2); the column left of the band holds round-off only
    col = lo[:, None] - 1 + np.arange(b + 1)[None, :]  # [n, b + 1]
    c_next = np.concatenate([c, np.zeros((n, 1))], axis=1)  # c[i, col + 1]
    c_here = np.concatenate([c[:, :1], c], axis=1)  # c[i, col]
    w_here = np.where(col <= n - 2, c_next * dt[np.clip(col, 0, n - 2)], 0.0)
    w_left = np.where(col >= 1, c_here * dt[np.clip(col - 1, 0, n - 2)], 0.0)
    s = (0.0 + w_here / 2) + w_left / 2
    s = np.where((col >= 0) & (col <= n - 1), s, 0.0)
    # the dense matrix has round-off entries left of the band too: below the threshold
    s[np.abs(s) < 1e-10 * np.abs(s).max()] = 0.0  # round-off of the zero row sums
    nonzero = s != 0
    any_nz = nonzero.any(axis=1)
    first = nonzero.argmax(axis=1)
    last = b - nonzero[:, ::-1].argmax(axis=1)
    lo_s = np.where(any_nz, col[np.arange(n), first], 0)
    hi_s = np.where(any_nz, col[np.arange(n), last], 0)
    width = int((hi_s - lo_s).max()) + 1
    index = np.minimum(lo_s[:, None] + np.arange(width)[None, :], n - 1)
    inside = lo_s[:, None] + np.arange(width)[None, :] <= hi_s[:, None]
    k = np.clip(index - (lo[:, None] - 1), 0, b)
    weight = np.where(inside, s[rows, k], 0.0)
    return index, weight


def synthetic_signal(
    rng: np.random.Generator,
    t: np.ndarray,
    events: Sequence[float] = (1.0, 1.1),
) -> tuple[np.ndarray, np.ndarray]:
    """A random signal like a generator state after a fault, and its exact derivative.

    The signal is flat before the first event; at every event it switches on two exponentials
    ``A (1 - exp(-(t - e)/tau))`` with ``tau`` log-uniform in [0.04, 1.5] s and a damped
    oscillation ``B exp(-a (t - e)) sin(2 pi f (t - e))`` with ``f`` uniform in [0.5, 2] Hz, so
    that ``x`` is continuous and ``dx/dt`` jumps at the events (as the states of a power system
    at a fault and its clearing). Returns ``(x, dxdt)`` on ``t``.
    """
    x = np.zeros_like(t)
    dx = np.zeros_like(t)
    for e in events:
        s = np.maximum(t - e, 0.0)
        on = t >= e
        for _ in range(2):
            A = rng.normal()
            tau = math.exp(rng.uniform(math.log(0.04), math.log(1.5)))
            x += on * A * (1.0 - np.exp(-s / tau))
            dx += on * A / tau * np.exp(-s / tau)
        B = rng.normal()
        f = rng.uniform(0.5, 2.0)
        a = rng.uniform(0.1, 1.0)
        w = 2 * math.pi * f
        x += on * B * np.exp(-a * s) * np.sin(w * s)
        dx += on * B * np.exp(-a * s) * (w * np.cos(w * s) - a * np.sin(w * s))
    return x, dx


def differentiation_error(
    method: Method = DEFAULT_METHOD,
    *,
    level: float = 0.01,
    n_signals: int = 50,
    seed: int = 0,
    split: bool = True,
    duration: float = 10.0,
    dt: float = 0.01,
    events: Sequence[float] = (1.0, 1.1),
    **kw: Any,
) -> dict[str, float]:
    """Relative RMS error of `differentiate` on noisy `synthetic_signal` records.

    Each of ``n_signals`` random signals (10 s at 0.01 s, events at 1.0 and 1.1 s) gets Gaussian
    noise with sigma = ``level`` x (max - min) of the signal. The error of a record is
    ``rms(dxdt_estimate - dxdt_exact) / std(dxdt_exact)``, and of the smoothed signal
    ``rms(x_smooth - x_exact) / std(x_exact)``. Returns the median and 90th percentile over the
    records (``"deriv_median"``, ``"deriv_p90"``, ``"value_median"``, ``"value_p90"``) and, for
    reference, the derivative error after the first 0.2 s of every segment
    (``"deriv_median_settled"``), where the fastest transients have died out.
    """
    rng = np.random.default_rng(seed)
    t = np.round(np.arange(0.0, duration + dt / 2, dt), 12)
    far = np.ones_like(t, dtype=bool)
    for e in events:
        far &= ~((t >= e - 1e-9) & (t < e + 0.2))
    errs, verrs, ferrs = [], [], []
    for _ in range(n_signals):
        x, dx = synthetic_signal(rng, t, events)
        noisy = x + rng.normal(size=t.shape) * level * float(np.ptp(x))
        xs, dxs = differentiate(t, noisy, events=events, method=method, split=split, **kw)
        errs.append(np.sqrt(np.mean((dxs - dx) ** 2)) / np.std(dx))
        verrs.append(np.sqrt(np.mean((xs - x) ** 2)) / np.std(x))
        ferrs.append(np.sqrt(np.mean((dxs - dx)[far] ** 2)) / np.std(dx))
    return {
        "deriv_median": float(np.median(errs)),
        "deriv_p90": float(np.percentile(errs, 90)),
        "value_median": float(np.median(verrs)),
        "value_p90": float(np.percentile(verrs, 90)),
        "deriv_median_settled": float(np.median(ferrs)),
    }


# ------------------------------------------------------------------------------------------------
# validation helpers
# ------------------------------------------------------------------------------------------------


def _check_time(t: ArrayLike, name: str = "t", minimum: int = 2) -> np.ndarray:
    """Sample times as float64 [n]: one-dimensional, finite, strictly increasing, n >= minimum."""
    try:
        arr = np.asarray(t, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise DataError(f"column {name!r} (time) is not numeric: {err}") from None
    if arr.ndim != 1:
        raise DataError(f"column {name!r} (time) must be one-dimensional, got shape {arr.shape}")
    if arr.shape[0] < minimum:
        why = (
            " (the derivative estimators fit local cubics and need a fifth sample to smooth; "
            "see jaxdmd.data.MIN_SAMPLES)"
            if minimum == MIN_SAMPLES
            else ""
        )
        raise DataError(
            f"column {name!r} (time) needs at least {minimum} samples, got {arr.shape[0]}{why}"
        )
    _check_finite(name, arr)
    step = np.diff(arr)
    if not np.all(step > 0):
        i = int(np.argmax(step <= 0))
        what = "repeated" if step[i] == 0 else "decreasing (unsorted)"
        raise DataError(
            f"column {name!r} (time) must be strictly increasing, but it is {what} at row "
            f"{i + 1}: t[{i}] = {arr[i]!r}, t[{i + 1}] = {arr[i + 1]!r}"
        )
    return arr


def time_key(header: str) -> str:
    """A column name as compared with the time names: units in parentheses or brackets dropped,
    lower case, spaces as ``_`` (``"Time (s)"`` -> ``"time"``, ``"Time s"`` -> ``"time_s"``)."""
    return "_".join(_UNITS.sub(" ", str(header)).lower().split())


def find_time_column(columns: Iterable[Any]) -> Any | None:
    """The first of ``columns`` named like a time column (`time_key` in ``t``, ``time``,
    ``time_s``, ``t_s``, ``timestamp``, ``seconds``), or None."""
    return next((c for c in columns if time_key(c) in _TIME_NAMES), None)


def _timestamp(cell: str) -> np.datetime64:
    """An ISO-8601 date or date-time as UTC nanoseconds; ValueError if it is not one."""
    m = _ISO.match(cell.strip())
    if m is None:
        raise ValueError(cell)
    stamp = np.datetime64(m.group(1).replace(" ", "T").replace(",", "."), "ns")
    zone = m.group(2)
    if zone and zone != "Z":
        digits = zone[1:].replace(":", "")
        minutes = int(digits[:2]) * 60 + (int(digits[2:]) if len(digits) > 2 else 0)
        offset = np.timedelta64(minutes, "m")
        stamp = stamp - offset if zone[0] == "+" else stamp + offset
    return stamp


def parse_times(values: Any, column: str = "t") -> np.ndarray:
    """Sample times in seconds from a time column: numbers (seconds) as they are; ``datetime64``
    values or ISO-8601 timestamps (``2024-05-01T12:00:00.25``, ``2024-05-01 12:00:00Z``,
    ``...+02:00``) as seconds from the first sample (offsets converted to UTC).

    Raises:
        DataError: naming the column and the first row that is neither a number nor a timestamp.
    """
    arr = np.asarray(values)
    if arr.dtype.kind == "M":
        ns = arr.astype("datetime64[ns]")
        if np.isnat(ns).any():
            i = int(np.argmax(np.isnat(ns)))
            raise DataError(f"column {column!r} (time) has a missing timestamp (NaT) at row {i}")
        return (ns - ns[0]).astype(np.int64) / 1e9
    if arr.dtype.kind in "biuf":
        return arr.astype(np.float64)
    cells = [str(v) for v in arr.ravel()]
    numbers = []
    for i, cell in enumerate(cells):
        try:
            numbers.append(float(cell))
        except ValueError:
            if i == 0:
                break  # timestamps, or an error named below
            what = "an empty cell" if not cell.strip() else f"non-numeric value {cell!r}"
            raise DataError(
                f"column {column!r} (time) has {what} at row {i} (the rows before are seconds)"
            ) from None
    else:
        return np.array(numbers, dtype=np.float64)
    stamps = np.empty(len(cells), dtype="datetime64[ns]")
    for i, cell in enumerate(cells):
        try:
            stamps[i] = _timestamp(cell)
        except ValueError:
            what = "an empty cell" if not cell.strip() else f"{cell!r}"
            raise DataError(
                f"column {column!r} (time) has {what} at row {i}: neither a number of seconds "
                "nor an ISO-8601 timestamp (e.g. 2024-05-01T12:00:00.25, optionally with Z or "
                "+02:00)"
            ) from None
    return (stamps - stamps[0]).astype(np.int64) / 1e9


def _check_events(
    events: Iterable[Any], span: tuple[float, float] | None = None
) -> tuple[float, ...]:
    """Event times as sorted distinct floats (`Dataset.create`, `Dataset.with_events`).

    Raises:
        DataError: an event that is not a number or not finite, or, with ``span`` = ``(t0,
            t1)``, one outside ``[t0, t1]`` (naming the time and the span).
    """
    evs: list[float] = []
    for e in events:
        try:
            ev = float(e)
        except (TypeError, ValueError):
            raise DataError(f"events must be numbers, got {e!r}") from None
        if not math.isfinite(ev):
            raise DataError(f"events must be finite, got {e!r}")
        if span is not None and not span[0] <= ev <= span[1]:
            raise DataError(
                f"event at t = {ev!r} s is outside the record's time span [{span[0]!r}, "
                f"{span[1]!r}] s"
            )
        evs.append(ev)
    return tuple(sorted(set(evs)))


def _check_finite(name: str, arr: np.ndarray, kind: str = "column") -> None:
    """Raise a DataError naming ``name`` and the first row holding a NaN or an infinity."""
    bad = ~np.isfinite(arr)
    if bad.any():
        i = int(np.argmax(bad))
        what = "NaN" if np.isnan(arr[i]) else "an infinite value"
        raise DataError(f"{kind} {name!r} has {what} at row {i} (first bad row)")


def _check_column(name: str, x: ArrayLike, n: int, kind: str = "column") -> np.ndarray:
    """A channel (or derivative) as float64 [n], finite."""
    try:
        arr = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise DataError(f"{kind} {name!r} is not numeric: {err}") from None
    if arr.ndim == 2 and arr.shape[1] == 1:
        arr = arr[:, 0]
    if arr.ndim != 1:
        raise DataError(f"{kind} {name!r} must be one-dimensional, got shape {arr.shape}")
    if arr.shape[0] != n:
        raise DataError(
            f"{kind} {name!r} has {arr.shape[0]} samples but t has {n} (unequal lengths)"
        )
    _check_finite(name, arr, kind)
    return arr


def _check_name(name: Any) -> str:
    """A channel name: it becomes a variable of the skeletons (spliced into their code), so it
    must be a Python identifier that is not a keyword, does not start with an underscore, and is
    not ``t``, ``p`` or a name the skeleton whitelist reserves (``sin``, ``jnp``, ``pi``)."""
    if not isinstance(name, str) or not name.strip():
        raise DataError(f"column names must be non-empty strings, got {name!r}")
    if name != name.strip():
        raise DataError(f"column {name!r} has leading or trailing whitespace in its name")
    if name.startswith(DERIVATIVE_PREFIX) or name == "t":
        raise DataError(
            f"column {name!r}: the name 't' and names starting with {DERIVATIVE_PREFIX!r} are "
            "reserved (time and derivative columns)"
        )
    why = invalid_variable_name(name)
    if why is not None:
        raise DataError(
            f"column {name!r} cannot be a model variable: {why}; rename it (e.g. "
            f"{_suggest(name)!r})"
        )
    return name


def _suggest(name: str) -> str:
    """A valid channel name close to ``name`` (for error messages)."""
    out = "".join(c if (c.isascii() and (c.isalnum() or c == "_")) else "_" for c in name)
    out = out.lstrip("_") or "x"
    if out[0].isdigit():
        out = "x" + out
    while invalid_variable_name(out) is not None:
        out += "_x"
    return out


def _pairs(
    items: Mapping[str, Any] | Sequence[tuple[str, Any]], what: str
) -> list[tuple[str, Any]]:
    """Name/value pairs from a mapping or a sequence of pairs, rejecting duplicate names."""
    pairs = list(items.items()) if isinstance(items, Mapping) else [tuple(p) for p in items]
    seen: set[str] = set()
    for pair in pairs:
        if len(pair) != 2:
            raise DataError(f"{what} must be (name, value) pairs, got {pair!r}")
        name = pair[0]
        if name in seen:
            raise DataError(f"column {name!r} appears more than once in {what} (duplicate name)")
        seen.add(name)
    return pairs  # type: ignore[return-value]


# ------------------------------------------------------------------------------------------------
# the Dataset
# ------------------------------------------------------------------------------------------------


class Dataset(eqx.Module):
    """One recording: times, channel values, state derivatives and static metadata.

    Build one with `Dataset.create` (which validates and, if needed, estimates derivatives) or
    `Dataset.load`. Array fields are the pytree leaves; everything else is static.

    Attributes:
        t: sample times in seconds [n], strictly increasing.
        values: channel values [n, c], channels as columns in the order of ``names``.
        derivatives: d/dt of the state channels [n, s], in the order of ``state_names``.
        names: channel names.
        roles: the role of every channel, one of `ROLES`.
        units: the unit of every channel ("" when unknown).
        events: known discontinuity times (fault on, fault clear), sorted.
        label: free text naming the recording.
    """

    t: np.ndarray
    values: np.ndarray
    derivatives: np.ndarray
    names: tuple[str, ...] = eqx.field(static=True)
    roles: tuple[str, ...] = eqx.field(static=True)
    units: tuple[str, ...] = eqx.field(static=True)
    events: tuple[float, ...] = eqx.field(static=True, default=())
    label: str = eqx.field(static=True, default="")

    def __check_init__(self) -> None:
        c, r, u = len(self.names), len(self.roles), len(self.units)
        if not c == r == u:
            raise DataError(f"{c} names, {r} roles and {u} units: they must match")
        if len(set(self.names)) != c:
            dup = next(nm for nm in self.names if self.names.count(nm) > 1)
            raise DataError(f"column {dup!r} appears more than once (duplicate name)")
        for name in self.names:
            _check_name(name)
        for name, role in zip(self.names, self.roles, strict=True):
            if role not in ROLES:
                raise DataError(f"column {name!r} has unknown role {role!r}; roles are {ROLES}")
        shapes = [getattr(a, "shape", None) for a in (self.t, self.values, self.derivatives)]
        if any(s is None for s in shapes):
            return  # placeholders (e.g. inside tree manipulations): nothing to check
        (ts, vs, ds) = shapes
        s = self.roles.count("state")
        if len(vs) < 2 or vs[-1] != c or vs[-2] != ts[-1]:
            raise DataError(f"values has shape {vs}; expected (n={ts[-1]}, channels={c})")
        if len(ds) < 2 or ds[-1] != s or ds[-2] != ts[-1]:
            raise DataError(f"derivatives has shape {ds}; expected (n={ts[-1]}, states={s})")

    # -- construction ---------------------------------------------------------------------------

    @classmethod
    def create(
        cls,
        t: ArrayLike,
        channels: Mapping[str, ArrayLike] | Sequence[tuple[str, ArrayLike]],
        roles: Mapping[str, str],
        units: Mapping[str, str] | None = None,
        derivatives: Mapping[str, ArrayLike] | Sequence[tuple[str, ArrayLike]] | None = None,
        events: Sequence[float] = (),
        label: str = "",
        **diff_kw: Any,
    ) -> Dataset:
        """Validate the inputs and build a Dataset.

        Args:
            t: sample times in seconds [n], strictly increasing.
            channels: channel name -> values [n] (a mapping, or a sequence of pairs).
            roles: channel name -> role (one of `ROLES`), for every channel.
            units: channel name -> unit; channels left out get "".
            derivatives: state name -> d/dt values [n], for every state channel, or None to
                estimate them with `differentiate` (piecewise between the ``events``).
            events: known discontinuity times (fault on, fault clear).
            label: free text naming the recording.
            **diff_kw: options of `differentiate` when derivatives are estimated.

        Raises:
            DataError: naming the column and the problem.
        """
        tt = _check_time(t, minimum=MIN_SAMPLES)
        n = tt.shape[0]
        pairs = _pairs(channels, "channels")
        names = tuple(_check_name(name) for name, _ in pairs)
        cols = [_check_column(name, x, n) for name, x in pairs]
        if not isinstance(roles, Mapping):
            raise DataError(f"roles must be a mapping name -> role, got {type(roles).__name__}")
        for name in roles:
            if name not in names:
                raise DataError(f"roles name column {name!r}, which is not among the channels")
        role_list = []
        for name in names:
            if name not in roles:
                raise DataError(f"column {name!r} has no role; give one of {ROLES}")
            role = roles[name]
            if role not in ROLES:
                raise DataError(f"column {name!r} has unknown role {role!r}; roles are {ROLES}")
            role_list.append(role)
        units = dict(units or {})
        for name in units:
            if name not in names:
                raise DataError(f"units name column {name!r}, which is not among the channels")
        unit_list = tuple(str(units.get(name, "")) for name in names)
        evs = _check_events(events)
        values = np.stack(cols, axis=1) if cols else np.zeros((n, 0))
        states = [nm for nm, r in zip(names, role_list, strict=True) if r == "state"]
        if derivatives is None:
            x = values[:, [names.index(s) for s in states]]
            _, dx = differentiate(tt, x, events=evs, **diff_kw) if states else (None, x)
        else:
            dpairs = dict(_pairs(derivatives, "derivatives"))
            for name in dpairs:
                if name not in states:
                    raise DataError(
                        f"derivatives given for column {name!r}, which is not a state channel"
                    )
            missing = [s for s in states if s not in dpairs]
            if missing:
                raise DataError(
                    f"state column {missing[0]!r} has no derivative: when derivatives are given,"
                    f" give one for every state (missing: {missing})"
                )
            dcols = [_check_column(s, dpairs[s], n, "derivative of column") for s in states]
            dx = np.stack(dcols, axis=1) if dcols else np.zeros((n, 0))
        return cls(
            t=tt,
            values=values,
            derivatives=np.ascontiguousarray(dx, dtype=np.float64),
            names=names,
            roles=tuple(role_list),
            units=unit_list,
            events=evs,
            label=str(label),
        )

    # -- access ---------------------------------------------------------------------------------

    def _index(self, name: str) -> int:
        try:
            return self.names.index(name)
        except ValueError:
            raise DataError(
                f"no column {name!r} in dataset {self.label!r}; columns are {self.names}"
            ) from None

    def __getitem__(self, name: str) -> np.ndarray:
        """The values [n] of channel ``name``."""
        return self.values[..., self._index(name)]

    def __contains__(self, name: object) -> bool:
        return name in self.names

    def derivative(self, name: str) -> np.ndarray:
        """d/dt [n] of state channel ``name``."""
        states = self.state_names
        if name not in states:
            self._index(name)
            raise DataError(f"column {name!r} is not a state (role {self.role(name)!r})")
        return self.derivatives[..., states.index(name)]

    def role(self, name: str) -> str:
        """The role of channel ``name``."""
        return self.roles[self._index(name)]

    def unit(self, name: str) -> str:
        """The unit of channel ``name``."""
        return self.units[self._index(name)]

    def names_with_role(self, role: str) -> tuple[str, ...]:
        """Channel names with the given role, in column order."""
        if role not in ROLES:
            raise DataError(f"unknown role {role!r}; roles are {ROLES}")
        return tuple(nm for nm, r in zip(self.names, self.roles, strict=True) if r == role)

    @property
    def state_names(self) -> tuple[str, ...]:
        """State channels, in the order of the columns of ``derivatives``."""
        return self.names_with_role("state")

    @property
    def algebraic_names(self) -> tuple[str, ...]:
        return self.names_with_role("algebraic")

    @property
    def input_names(self) -> tuple[str, ...]:
        return self.names_with_role("input")

    @property
    def boundary_names(self) -> tuple[str, ...]:
        return self.names_with_role("boundary")

    @property
    def n_samples(self) -> int:
        return int(self.t.shape[-1])

    @property
    def dt(self) -> float:
        """The median sampling step in seconds."""
        return float(np.median(np.diff(np.asarray(self.t))))

    def channels(self) -> dict[str, np.ndarray]:
        """All channels as a dict name -> values [n] (numpy)."""
        v = np.asarray(self.values)
        return {nm: v[:, i] for i, nm in enumerate(self.names)}

    def derivative_dict(self) -> dict[str, np.ndarray]:
        """All state derivatives as a dict state name -> d/dt values [n] (numpy)."""
        d = np.asarray(self.derivatives)
        return {nm: d[:, i] for i, nm in enumerate(self.state_names)}

    def samples(self, names: Sequence[str]) -> dict[str, np.ndarray]:
        """`stack_samples` of this dataset alone."""
        return stack_samples([self], names)

    # -- derived datasets -----------------------------------------------------------------------

    def _rebuild(self, **changes: Any) -> Dataset:
        fields = {
            "t": self.t,
            "values": self.values,
            "derivatives": self.derivatives,
            "names": self.names,
            "roles": self.roles,
            "units": self.units,
            "events": self.events,
            "label": self.label,
        }
        fields.update(changes)
        return Dataset(**fields)

    def select(self, names: Sequence[str]) -> Dataset:
        """A dataset with only the given channels (and the derivatives of its states)."""
        names = tuple(names)
        idx = [self._index(nm) for nm in names]
        if len(set(names)) != len(names):
            dup = next(nm for nm in names if names.count(nm) > 1)
            raise DataError(f"column {dup!r} selected more than once (duplicate name)")
        states = self.state_names
        kept_states = [nm for nm in names if self.role(nm) == "state"]
        didx = [states.index(nm) for nm in kept_states]
        return self._rebuild(
            values=np.asarray(self.values)[:, idx],
            derivatives=np.asarray(self.derivatives)[:, didx],
            names=names,
            roles=tuple(self.roles[i] for i in idx),
            units=tuple(self.units[i] for i in idx),
        )

    def with_channels(
        self,
        channels: Mapping[str, ArrayLike] | Sequence[tuple[str, ArrayLike]],
        roles: Mapping[str, str],
        units: Mapping[str, str] | None = None,
        derivatives: Mapping[str, ArrayLike] | None = None,
        **diff_kw: Any,
    ) -> Dataset:
        """A dataset with extra channels appended (their names must be new).

        New state channels take their derivatives from ``derivatives`` or, if it is None, have
        them estimated with `differentiate`; the existing derivatives are kept.
        """
        new = _pairs(channels, "channels")
        all_pairs = list(self.channels().items()) + new
        all_roles = dict(zip(self.names, self.roles, strict=True)) | dict(roles)
        all_units = dict(zip(self.names, self.units, strict=True)) | dict(units or {})
        ders: dict[str, Any] = self.derivative_dict()
        new_states = [nm for nm, _ in new if roles.get(nm) == "state"]
        if derivatives is not None:
            ders |= dict(derivatives)
        else:
            for nm, x in new:
                if nm in new_states:
                    col = _check_column(nm, x, self.n_samples)
                    ders[nm] = differentiate(self.t, col, events=self.events, **diff_kw)[1]
        return Dataset.create(
            self.t,
            all_pairs,
            all_roles,
            all_units,
            derivatives=ders,
            events=self.events,
            label=self.label,
        )

    def with_time(self, name: str = "time") -> Dataset:
        """The recording with its time axis as an input channel (unit ``s``): a candidate
        variable for a forcing that depends on time (the offline proposer offers sin(w t) and
        cos(w t) of it, w fitted). Leave it out for an autonomous component: its equations do
        not depend on when the recording started."""
        return self.with_channels({name: np.asarray(self.t)}, {name: "input"}, {name: "s"})

    def window(self, t0: float, t1: float) -> Dataset:
        """The samples with ``t0 <= t <= t1`` (e.g. a held-out window), events inside kept.

        Derivatives are sliced, not re-estimated (estimates from the whole record are better).
        """
        t = np.asarray(self.t)
        keep = (t >= t0) & (t <= t1)
        if keep.sum() < 2:
            raise DataError(
                f"column 't': window [{t0}, {t1}] holds {int(keep.sum())} samples; need >= 2 "
                f"(record spans [{t[0]}, {t[-1]}])"
            )
        return self._rebuild(
            t=t[keep],
            values=np.asarray(self.values)[keep],
            derivatives=np.asarray(self.derivatives)[keep],
            events=tuple(e for e in self.events if t0 <= e <= t1),
        )

    def with_values(self, values: Mapping[str, ArrayLike]) -> Dataset:
        """The same recording with the samples of existing channels replaced (for instance the
        states by an estimate of them); derivatives, roles and events are kept."""
        out = np.array(self.values, dtype=np.float64)
        for name, column in values.items():
            out[:, self._index(name)] = _check_column(name, column, self.n_samples)
        return self._rebuild(values=out)

    def with_noise(
        self,
        key: Any,
        level: float = 0.01,
        roles: Sequence[str] = ("state",),
        names: Sequence[str] | None = None,
        **diff_kw: Any,
    ) -> Dataset:
        """Add Gaussian noise with sigma = ``level`` x (max - min) of each noisy channel.

        The noisy channels are those with a role in ``roles`` (or exactly ``names``, if given).
        ``key`` is a JAX PRNG key (or an int seed). If any state got noise, the derivatives are
        re-estimated from the noisy states with `differentiate` (options ``diff_kw``).
        """
        import jax

        if isinstance(key, int):
            key = jax.random.key(key)
        for r in roles:
            if r not in ROLES:
                raise DataError(f"unknown role {r!r}; roles are {ROLES}")
        if level < 0:
            raise DataError(f"noise level must be >= 0, got {level}")
        chosen = (
            tuple(names)
            if names is not None
            else tuple(nm for nm, r in zip(self.names, self.roles, strict=True) if r in roles)
        )
        idx = [self._index(nm) for nm in chosen]
        values = np.array(self.values, dtype=np.float64)
        noise = np.asarray(jax.random.normal(key, values.shape, dtype=jax.numpy.float64))
        sigma = level * np.ptp(values, axis=0)
        values[:, idx] += noise[:, idx] * sigma[idx]
        noisy = self._rebuild(values=values)
        if any(self.roles[i] == "state" for i in idx):
            return noisy.with_estimated_derivatives(**diff_kw)
        return noisy

    def with_estimated_derivatives(
        self, method: Method = DEFAULT_METHOD, *, smooth: bool = False, **kw: Any
    ) -> Dataset:
        """Re-estimate the state derivatives with `differentiate`, split at the events.

        With ``smooth=True`` the state values are replaced by their smoothed estimates as well
        (useful as regressors when the states are noisy).
        """
        states = self.state_names
        if not states:
            return self
        sidx = [self._index(nm) for nm in states]
        values = np.array(self.values, dtype=np.float64)
        xs, dx = differentiate(self.t, values[:, sidx], events=self.events, method=method, **kw)
        if smooth:
            values[:, sidx] = xs
        return self._rebuild(values=values, derivatives=dx)

    def with_events(self, events: Iterable[float], **diff_kw: Any) -> Dataset:
        """The same recording with the event times ``events`` (fault on, fault clear) in place
        of its own.

        The times are checked as `create` checks them (numbers, finite; sorted, duplicates
        dropped) and must lie in the record's time span ``[t[0], t[-1]]``. If the recording has
        states, their derivatives are re-estimated with `differentiate` split at the new events
        (options ``diff_kw``), as `create` estimates them when none are given: a `Dataset` does
        not record whether its derivatives were estimated, and estimates split at the wrong
        events smear the jumps. Derivatives given to `create` (exact ones, from a simulator) are
        replaced as well; to keep them, give the events when building or loading the recording
        (``Dataset.create(..., events=...)``, ``Dataset.load(path, events=...)``). The values
        are kept.

        Raises:
            DataError: an event that is not a finite number, or one outside the time span
                (naming the time and the span).
        """
        t = np.asarray(self.t)
        evs = _check_events(events, span=(float(t[0]), float(t[-1])))
        return self._rebuild(events=evs).with_estimated_derivatives(**diff_kw)

    # -- I/O ------------------------------------------------------------------------------------

    def _meta(self) -> dict[str, Any]:
        return {
            "format": _FORMAT,
            "version": _VERSION,
            "time": "t",
            "label": self.label,
            "events": list(self.events),
            "roles": dict(zip(self.names, self.roles, strict=True)),
            "units": dict(zip(self.names, self.units, strict=True)),
        }

    def save(self, path: str | Path) -> Path:
        """Save as ``.npz`` (arrays and metadata), or as ``.csv`` plus a JSON sidecar.

        The CSV has a column ``t``, one column per channel and one column ``d/dt <state>`` per
        state; the sidecar ``<path>.json`` (e.g. ``run.csv.json``) names the roles, units,
        events and label. Returns the path written.
        """
        path = Path(path)
        if path.suffix == ".npz":
            np.savez(
                path,
                t=np.asarray(self.t, dtype=np.float64),
                values=np.asarray(self.values, dtype=np.float64),
                derivatives=np.asarray(self.derivatives, dtype=np.float64),
                meta=np.array(json.dumps({**self._meta(), "names": list(self.names)})),
            )
        elif path.suffix == ".csv":
            header = ["t", *self.names, *(DERIVATIVE_PREFIX + s for s in self.state_names)]
            table = np.column_stack(
                [np.asarray(self.t), np.asarray(self.values), np.asarray(self.derivatives)]
            )
            with path.open("w", newline="") as f:
                w = csv.writer(f)
                w.writerow(header)
                w.writerows([repr(float(v)) for v in row] for row in table)
            sidecar = _sidecar_paths(path)[0]
            sidecar.write_text(json.dumps(self._meta(), indent=2) + "\n")
        else:
            raise DataError(f"save: unknown file type {path.suffix!r} of {path}; use .npz or .csv")
        return path

    @staticmethod
    def load(
        path: str | Path,
        *,
        roles: Mapping[str, str] | None = None,
        units: Mapping[str, str] | None = None,
        events: Sequence[float] | None = None,
        label: str | None = None,
        **diff_kw: Any,
    ) -> Dataset:
        """Load a ``.npz`` written by `save`, a ``.csv`` with its JSON sidecar, or a COMTRADE
        recording (``.cfg`` with its ``.dat``, or ``.cff``; `_load_comtrade`).

        The sidecar is ``<path>.json`` or ``<path without suffix>.json``; it holds ``roles`` and
        optionally ``units``, ``events``, ``label`` and ``time`` (the time column; default: a
        column named ``t`` or ``time``). Keyword arguments override (or replace) the sidecar.
        CSV columns ``d/dt <state>`` are the state derivatives; without them, derivatives are
        estimated (options ``diff_kw``).
        """
        path = Path(path)
        if not path.exists():
            raise DataFileNotFound(f"{path}: not found (no such data file)")
        if path.is_dir():
            raise DataError(f"{path}: is a directory, not a data file (.npz or .csv)")
        try:
            if path.suffix == ".npz":
                return _load_npz(path, roles, units, events, label)
            if path.suffix == ".csv":
                return _load_csv(path, roles, units, events, label, diff_kw)
            if path.suffix.lower() in COMTRADE_SUFFIXES:
                return _load_comtrade(path, roles, units, events, label, diff_kw)
        except DataError as err:
            raise _in_file(err, path) from None
        except (OSError, ValueError, KeyError, TypeError, EOFError, zipfile.BadZipFile) as err:
            # unreadable or malformed files (a damaged .npz, bad metadata): a DataError too
            what = type(err).__name__
            raise DataError(f"{path}: cannot be read as a jaxdmd dataset ({what}: {err})") from None
        raise DataError(
            f"load: unknown file type {path.suffix!r} of {path}; use .npz, .csv or COMTRADE "
            "(.cfg with its .dat, or .cff)"
        )

    @classmethod
    def from_frame(
        cls,
        df: Any,
        roles: Mapping[str, str],
        time: Any = None,
        units: Mapping[str, str] | None = None,
        events: Sequence[float] = (),
        label: str = "",
        **diff_kw: Any,
    ) -> Dataset:
        """A Dataset from a table with named columns: a pandas ``DataFrame`` or anything with
        ``.columns`` and ``df[column]`` returning an array-like (pandas is optional and not
        imported here).

        Args:
            df: the table; columns ``d/dt <state>`` are state derivatives (else estimated).
            roles: column name -> role for every other column except the time column.
            time: the time column; None: a column named like a time column (``t``, ``time``,
                ``Time (s)``, ``timestamp``, ...), else the frame's index (a ``DatetimeIndex``
                or numeric times; not a plain row-number ``RangeIndex``). Numbers are seconds;
                ``datetime64`` values and ISO-8601 strings become seconds from the first sample.
            units, events, label, **diff_kw: as `create`.

        Raises:
            DataError: naming the column and the problem.
        """
        keys = list(df.columns)
        names = [str(k) for k in keys]
        key_of = dict(zip(names, keys, strict=True))
        if time is None:
            time_name = find_time_column(names)
            if time_name is not None:
                t = parse_times(_array(df[key_of[time_name]]), time_name)
            else:
                index = getattr(df, "index", None)
                if index is None or type(index).__name__ == "RangeIndex":
                    raise DataError(
                        f"the frame has no time column (expected one named {_TIME_NAMES}, in "
                        f"any case, units in parentheses ignored) and "
                        f"{'no index' if index is None else 'only a row-number index'}; pass "
                        f"time=COLUMN (its columns: {', '.join(names)})"
                    )
                t = parse_times(_array(index), str(getattr(index, "name", None) or "index"))
        else:
            time_name = str(time)
            if time_name not in key_of:
                raise DataError(
                    f"time={time_name!r} names a column the frame lacks (its columns: "
                    f"{', '.join(names)})"
                )
            t = parse_times(_array(df[key_of[time_name]]), time_name)
        if not isinstance(roles, Mapping):
            raise DataError(f"roles must be a mapping name -> role, got {type(roles).__name__}")
        for src, group in (("roles", roles), ("units", units or {})):
            for nm in group:
                if nm not in key_of:
                    raise DataError(
                        f"{src} name column {nm!r}, which the frame lacks (its columns: "
                        f"{', '.join(names)})"
                    )
        channels, ders = [], {}
        for nm in names:
            if nm == time_name:
                continue
            if nm.startswith(DERIVATIVE_PREFIX):
                state = nm[len(DERIVATIVE_PREFIX) :]
                if state not in key_of:
                    raise DataError(
                        f"column {nm!r} is the derivative of {state!r}, which is absent"
                    )
                ders[state] = _array(df[key_of[nm]])
            elif nm not in roles:
                raise DataError(f"column {nm!r} of the frame has no role; give one of {ROLES}")
            else:
                channels.append((nm, _array(df[key_of[nm]])))
        return cls.create(
            t, channels, roles, units, derivatives=ders or None, events=events, label=label,
            **diff_kw,
        )  # fmt: skip


def _array(x: Any) -> np.ndarray:
    """A column of a frame as a numpy array (a pandas Series through ``to_numpy``)."""
    to_numpy = getattr(x, "to_numpy", None)
    return np.asarray(to_numpy() if callable(to_numpy) else x)


def stored_roles(path: str | Path) -> dict[str, str]:
    """The roles a data file carries: a CSV's (or COMTRADE file's) sidecar ``roles`` or an
    ``.npz``'s; ``{}`` when there are none (no sidecar)."""
    path = Path(path)
    if path.suffix == ".npz" and path.is_file():
        with np.load(path, allow_pickle=False) as z:
            if "meta" in z.files:
                return dict(json.loads(str(z["meta"])).get("roles", {}))
        return {}
    meta = _read_sidecar(path) if path.suffix.lower() in (".csv", *COMTRADE_SUFFIXES) else None
    roles = (meta or {}).get("roles", {})
    return dict(roles) if isinstance(roles, Mapping) else {}


def data_columns(path: str | Path) -> list[str]:
    """The channel columns of a data file, which need a role: a CSV's header without its time
    column and the ``d/dt`` columns, an ``.npz``'s channel names, or a COMTRADE file's analog
    channels."""
    path = Path(path)
    if not path.exists():
        raise DataFileNotFound(f"{path}: not found (no such data file)")
    if path.suffix == ".npz":
        with np.load(path, allow_pickle=False) as z:
            return list(json.loads(str(z["meta"]))["names"]) if "meta" in z.files else []
    if path.suffix.lower() in COMTRADE_SUFFIXES:
        return [str(c).strip() for c in _comtrade_record(path).analog_channel_ids]
    with path.open(newline="") as f:
        header = next((r for r in csv.reader(f) if r and not r[0].lstrip().startswith("#")), [])
    header = [h.strip() for h in header]
    time_col = (_read_sidecar(path) or {}).get("time") or find_time_column(header)
    return [h for h in header if h != time_col and not h.startswith(DERIVATIVE_PREFIX)]


# ------------------------------------------------------------------------------------------------
# I/O helpers
# ------------------------------------------------------------------------------------------------


def _sidecar_paths(path: Path) -> tuple[Path, Path]:
    return path.with_name(path.name + ".json"), path.with_suffix(".json")


def _read_sidecar(path: Path) -> dict[str, Any] | None:
    for side in _sidecar_paths(path):
        if side.exists():
            try:
                meta = json.loads(side.read_text())
            except json.JSONDecodeError as err:
                raise DataError(f"sidecar {side} is not valid JSON: {err}") from None
            if not isinstance(meta, dict):
                raise DataError(f"sidecar {side} must hold a JSON object")
            meta["_path"] = str(side)
            return meta
    return None


def _load_npz(
    path: Path,
    roles: Mapping[str, str] | None,
    units: Mapping[str, str] | None,
    events: Sequence[float] | None,
    label: str | None,
) -> Dataset:
    with np.load(path, allow_pickle=False) as z:
        missing = [k for k in ("t", "values", "derivatives", "meta") if k not in z.files]
        if missing:
            raise DataError(f"{path}: not a jaxdmd dataset, missing arrays {missing}")
        t, values, ders = z["t"], z["values"], z["derivatives"]
        meta = json.loads(str(z["meta"]))
    names = meta["names"]
    if values.ndim != 2 or values.shape[1] != len(names):
        raise DataError(f"{path}: values has shape {values.shape} for {len(names)} names")
    roles = dict(roles) if roles is not None else meta["roles"]
    states = [nm for nm in names if roles.get(nm) == "state"]
    if ders.ndim != 2 or ders.shape[1] != len(states):
        raise DataError(f"{path}: derivatives has shape {ders.shape} for {len(states)} states")
    return Dataset.create(
        t,
        [(nm, values[:, i]) for i, nm in enumerate(names)],
        roles,
        dict(units) if units is not None else meta.get("units", {}),
        derivatives={s: ders[:, i] for i, s in enumerate(states)},
        events=tuple(events) if events is not None else tuple(meta.get("events", ())),
        label=label if label is not None else meta.get("label", ""),
    )


def _load_csv(
    path: Path,
    roles: Mapping[str, str] | None,
    units: Mapping[str, str] | None,
    events: Sequence[float] | None,
    label: str | None,
    diff_kw: Mapping[str, Any],
) -> Dataset:
    meta = _read_sidecar(path) or {}
    side = meta.get("_path", "the sidecar")
    if roles is None:
        if "roles" not in meta:
            raise DataError(
                f"{path}: no sidecar ({' or '.join(map(str, _sidecar_paths(path)))}) naming the "
                "roles; write one or pass roles= to Dataset.load (on the command line: "
                "--states, --algebraic, --inputs, --boundary or --role NAME=ROLE)"
            )
        roles = meta["roles"]
        role_src = side
    else:
        role_src = "the roles given"
    if not isinstance(roles, Mapping):
        raise DataError(f"{side}: 'roles' must map column names to roles")
    units = units if units is not None else meta.get("units", {})
    events = events if events is not None else meta.get("events", ())
    label = label if label is not None else meta.get("label", path.stem)

    with path.open(newline="") as f:
        rows = [r for r in csv.reader(f) if r and not r[0].lstrip().startswith("#")]
    if not rows:
        raise DataError(f"{path}: empty CSV (no header)")
    header = [h.strip() for h in rows[0]]
    seen: set[str] = set()
    for h in header:
        if not h:
            raise DataError(f"{path}: the header has an empty column name")
        if h in seen:
            raise DataError(f"{path}: column {h!r} appears more than once (duplicate name)")
        seen.add(h)
    time_col = meta.get("time")
    if time_col is None:
        time_col = find_time_column(header)
        if time_col is None:
            raise DataError(
                f"{path}: the CSV has no time column (expected one named {_TIME_NAMES}, in any "
                f"case, units in parentheses ignored, e.g. 'Time (s)'; or a 'time' entry in the "
                f"sidecar); columns are {header}"
            )
    elif time_col not in header:
        raise DataError(f"{side} names time column {time_col!r}, which the CSV {path} lacks")
    for src, group in ((role_src, roles), (side, units)):
        for nm in group:
            if nm not in header:
                raise DataError(
                    f"{src} names column {nm!r}, which the CSV {path} lacks (its columns: "
                    f"{', '.join(header)})"
                )

    body = rows[1:]
    tj = header.index(time_col)
    table = np.empty((len(body), len(header)))
    for i, row in enumerate(body):
        if len(row) != len(header):
            short = header[len(row)] if len(row) < len(header) else None
            what = f"column {short!r} is missing" if short else "it has extra fields"
            raise DataError(
                f"{path}: data row {i} has {len(row)} fields but the header has {len(header)} "
                f"(unequal lengths: {what})"
            )
        for j, cell in enumerate(row):
            if j == tj:
                continue  # seconds or timestamps: parse_times below
            try:
                table[i, j] = float(cell)
            except ValueError:
                what = "an empty cell" if not cell.strip() else f"non-numeric value {cell!r}"
                raise DataError(f"column {header[j]!r} has {what} at row {i}") from None

    col = {h: table[:, j] for j, h in enumerate(header)}
    t = parse_times([row[tj] for row in body], time_col)
    channels, ders = [], {}
    for h in header:
        if h == time_col:
            continue
        if h.startswith(DERIVATIVE_PREFIX):
            state = h[len(DERIVATIVE_PREFIX) :]
            if state not in header:
                raise DataError(f"column {h!r} is the derivative of {state!r}, which is absent")
            ders[state] = col[h]
        else:
            if h not in roles:
                raise DataError(
                    f"column {h!r} of {path} has no role in {role_src}; give one of {ROLES} (on "
                    f"the command line: --states/--algebraic/--inputs/--boundary {h}, or "
                    f"--role {h}=ROLE)"
                )
            channels.append((h, col[h]))
    return Dataset.create(
        t,
        channels,
        roles,
        units,
        derivatives=ders or None,
        events=tuple(events),
        label=str(label),
        **diff_kw,
    )


COMTRADE_SUFFIXES: tuple[str, ...] = (".cfg", ".cff")
"""File suffixes read as COMTRADE (IEEE C37.111) through the optional package ``comtrade``."""


def _comtrade_record(path: Path) -> Any:
    """The recording read by the ``comtrade`` package (optional: ``pip install
    'jaxdmd[comtrade]'``), in float64."""
    try:
        import comtrade
    except ImportError:
        raise DataError(
            f"{path}: reading COMTRADE needs the optional package 'comtrade' (pip install "
            "'jaxdmd[comtrade]'), or convert the recording to CSV"
        ) from None
    rec = comtrade.Comtrade(use_double_precision=True, use_numpy_arrays=True)
    try:
        rec.load(str(path))
    except (comtrade.ComtradeError, OSError, ValueError, IndexError, KeyError, TypeError) as err:
        what = type(err).__name__
        raise DataError(f"{path}: cannot be read as COMTRADE ({what}: {err})") from None
    return rec


def _load_comtrade(
    path: Path,
    roles: Mapping[str, str] | None,
    units: Mapping[str, str] | None,
    events: Sequence[float] | None,
    label: str | None,
    diff_kw: Mapping[str, Any],
) -> Dataset:
    """A COMTRADE recording: its analog channels (named by their channel ids, which must be
    valid variable names; the status channels are left out), the time in seconds from the
    first sample, the channel units of the .cfg; roles, events and label from the sidecar
    (``rec.cfg.json`` or ``rec.json``) or the arguments, as for a CSV."""
    meta = _read_sidecar(path) or {}
    side = meta.get("_path", "the sidecar")
    if roles is None:
        if "roles" not in meta:
            raise DataError(
                f"{path}: no sidecar ({' or '.join(map(str, _sidecar_paths(path)))}) naming the "
                "roles; write one or pass roles= to Dataset.load (on the command line: "
                "--states, --algebraic, --inputs, --boundary or --role NAME=ROLE)"
            )
        roles, role_src = meta["roles"], side
    else:
        role_src = "the roles given"
    if not isinstance(roles, Mapping):
        raise DataError(f"{side}: 'roles' must map channel names to roles")
    rec = _comtrade_record(path)
    names = [str(c).strip() for c in rec.analog_channel_ids]
    seen: set[str] = set()
    for nm in names:
        if nm in seen:
            raise DataError(f"{path}: analog channel {nm!r} appears more than once")
        seen.add(nm)
    stored_units = {
        nm: str(getattr(ch, "uu", "") or "").strip()
        for nm, ch in zip(names, rec.cfg.analog_channels, strict=True)
    }
    units = units if units is not None else meta.get("units", stored_units)
    for src, group in ((role_src, roles), (side, units)):
        for nm in group:
            if nm not in names:
                raise DataError(
                    f"{src} names column {nm!r}, which the COMTRADE file {path} lacks (its "
                    f"analog channels: {', '.join(names)})"
                )
    for nm in names:
        if nm not in roles:
            raise DataError(
                f"column {nm!r} of {path} has no role in {role_src}; give one of {ROLES} (on "
                f"the command line: --states/--algebraic/--inputs/--boundary {nm}, or "
                f"--role {nm}=ROLE)"
            )
    t = np.asarray(rec.time, dtype=np.float64)
    t = t - t[0] if t.size else t
    channels = [(nm, np.asarray(rec.analog[i], dtype=np.float64)) for i, nm in enumerate(names)]
    return Dataset.create(
        t,
        channels,
        roles,
        units,
        events=tuple(events if events is not None else meta.get("events", ())),
        label=str(label if label is not None else meta.get("label", path.stem)),
        **diff_kw,
    )


def check_compatible(
    datasets: Sequence[Dataset], paths: Sequence[str | Path] | None = None
) -> None:
    """Raise `DataError` unless the recordings can be fitted together.

    They must have the same channels in the same order, with the same roles, and the same units
    where both give one. Their lengths, sampling rates (even non-uniform grids) and events may
    differ: the pipeline concatenates the samples and gives every recording its own estimator
    and integration operators. The message names both recordings: ``paths`` (the files they were
    read from) if given, else their labels.
    """
    datasets = list(datasets)
    if paths is not None and len(paths) != len(datasets):
        raise ValueError(f"{len(paths)} paths for {len(datasets)} datasets")

    def where(i: int) -> str:
        if paths is not None:
            return str(paths[i])
        return repr(datasets[i].label) if datasets[i].label else f"recording {i}"

    if not datasets:
        return
    first = datasets[0]
    for i, ds in enumerate(datasets[1:], start=1):
        if ds.names != first.names:
            missing = [nm for nm in first.names if nm not in ds.names]
            extra = [nm for nm in ds.names if nm not in first.names]
            parts = [f"lacks {missing}"] if missing else []
            parts += [f"has the extra channels {extra}"] if extra else []
            what = " and ".join(parts) or (
                f"orders them differently ({list(ds.names)} vs {list(first.names)})"
            )
            raise DataError(
                f"{where(i)}: its channels differ from those of {where(0)}: it {what}; "
                "recordings fitted together need the same channels"
            )
        for nm, r0, r1, u0, u1 in zip(
            first.names, first.roles, ds.roles, first.units, ds.units, strict=True
        ):
            if r0 != r1:
                raise DataError(
                    f"{where(i)}: column {nm!r} has the role {r1!r}, but {r0!r} in {where(0)}"
                )
            if u0 and u1 and u0 != u1:
                raise DataError(
                    f"{where(i)}: column {nm!r} is in {u1!r}, but in {u0!r} in {where(0)}"
                )


def load_many(paths: Sequence[str | Path], **kw: Any) -> list[Dataset]:
    """`Dataset.load` every path (errors name the file), then `check_compatible` them."""
    datasets = [Dataset.load(p, **kw) for p in paths]
    check_compatible(datasets, paths)
    return datasets


def stack_samples(datasets: Sequence[Dataset], names: Sequence[str]) -> dict[str, np.ndarray]:
    """Concatenate channels of several recordings (for fitting on all of them at once).

    ``names`` may hold channel names, ``"t"`` and ``"d/dt <state>"`` (state derivatives).
    Returns a dict name -> numpy float64 array [sum of n].
    """
    if isinstance(datasets, Dataset):
        datasets = [datasets]
    if not datasets:
        raise DataError("stack_samples: no datasets")
    out: dict[str, list[np.ndarray]] = {nm: [] for nm in names}
    for ds in datasets:
        for nm in names:
            if nm == "t":
                out[nm].append(np.asarray(ds.t, dtype=np.float64))
            elif nm.startswith(DERIVATIVE_PREFIX):
                out[nm].append(np.asarray(ds.derivative(nm[len(DERIVATIVE_PREFIX) :])))
            else:
                out[nm].append(np.asarray(ds[nm], dtype=np.float64))
    return {nm: np.concatenate(v) for nm, v in out.items()}


samples: Callable[[Sequence[Dataset], Sequence[str]], dict[str, np.ndarray]] = stack_samples
"""Alias of `stack_samples`."""
