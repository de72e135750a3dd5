"""Putting one irregularly sampled stream onto a uniform grid: its own rate, linear interpolation,
a zero-phase anti-alias low-pass for a faster source, and the mask of grid points inside gaps.

`SetAside` is the one error of signal processing: a trial that cannot be aligned or resampled.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.signal import butter, sosfiltfilt

from needlecue_runtime import vocab

# A source counts as "faster than the grid" only above this margin: a 30.02 Hz host stream
# onto a 30 Hz grid has nothing to alias, and filtering it would only blur it.
FASTER_MARGIN = 1.05
CUTOFF_FRACTION = 0.8  # anti-alias cutoff as a fraction of the target Nyquist frequency


class SetAside(Exception):
    """A trial that cannot be aligned or resampled; the message is the reason."""


def median_rate(t: np.ndarray) -> float:
    """Sample rate (Hz) of a stream from its median interval (`vocab.rate_hz`); SetAside if none."""
    rate = vocab.rate_hz(t)
    if math.isnan(rate):
        raise SetAside("stream has fewer than two distinct time stamps")
    return rate


def to_uniform(t: np.ndarray, x: np.ndarray, rate_hz: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Linear interpolation of an irregular stream onto its own uniform grid (median rate by default).

    Gaps are bridged here; `gap_mask` later drops whatever grid point falls inside one.
    """
    t = np.asarray(t, dtype=np.float64)
    rate = median_rate(t) if rate_hz is None else rate_hz
    n = math.floor((t[-1] - t[0]) * rate + 1e-9) + 1
    tu = t[0] + np.arange(n) / rate
    return tu, interp_columns(tu, t, x)


def interp_columns(tq: np.ndarray, t: np.ndarray, x: np.ndarray) -> np.ndarray:
    """np.interp applied to every column of `x` (n, k) or to a 1-D `x`."""
    x = np.asarray(x, dtype=np.float64)
    if x.ndim == 1:
        return np.interp(tq, t, x)
    return np.stack([np.interp(tq, t, x[:, k]) for k in range(x.shape[1])], axis=1)


def lowpass(x: np.ndarray, fs_hz: float, cutoff_hz: float, order: int) -> np.ndarray:
    """Zero-phase Butterworth low-pass along axis 0 (filtfilt: no delay, so no clock bias)."""
    x = np.asarray(x, dtype=np.float64)
    if cutoff_hz >= 0.5 * fs_hz or x.shape[0] < 4:
        return x
    sos = butter(order, cutoff_hz, btype="low", fs=fs_hz, output="sos")
    padlen = min(3 * (2 * len(sos) + 1), x.shape[0] - 1)
    return sosfiltfilt(sos, x, axis=0, padlen=padlen)


def gap_mask(t_src: np.ndarray, t_query: np.ndarray, max_gap_s: float) -> np.ndarray:
    """True for query times strictly inside an interval longer than `max_gap_s` between samples."""
    t_src = np.asarray(t_src, dtype=np.float64)
    t_query = np.asarray(t_query, dtype=np.float64)
    if t_src.size < 2:
        return np.ones(t_query.shape, dtype=bool)
    i = np.searchsorted(t_src, t_query, side="right") - 1
    ok = (i >= 0) & (i < t_src.size - 1)
    ic = np.clip(i, 0, t_src.size - 2)
    long_gap = (t_src[ic + 1] - t_src[ic]) > max_gap_s
    return ok & long_gap & (t_query > t_src[ic]) & (t_query < t_src[ic + 1])


def resample_stream(t: np.ndarray, x: np.ndarray, grid: np.ndarray, rate_hz: float, order: int) -> np.ndarray:
    """One stream onto `grid`: own uniform grid first, then anti-alias if faster, then interpolate."""
    tu, xu = to_uniform(t, x)
    fs = 1.0 / (tu[1] - tu[0]) if tu.size > 1 else rate_hz
    if fs > FASTER_MARGIN * rate_hz:
        xu = lowpass(xu, fs, CUTOFF_FRACTION * 0.5 * rate_hz, order)
    return interp_columns(grid, tu, xu)
