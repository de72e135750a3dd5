"""`resample` stage: align the two clocks of every trial and put both streams on one grid.

Input: the ingest stage's accepted batches, `IN_DIR/<batch_id>/{batch.json, trials.parquet,
fsr.parquet, ref.parquet}` (folders without `trials.parquet` were set aside by ingest and
are skipped). Per trial:

1. units: ADC counts -> volts, mN -> N;
2. clock offset estimated from the signals (`estimate_offset`), never from the two t=0;
3. both streams resampled onto one uniform grid at `rate_hz` over their overlap, with a
   zero-phase anti-alias filter for a faster source and grid points in gaps dropped;
4. a phase label per grid sample from the reference force (`label_phases`).

Output: `OUT_DIR/<batch_id>.parquet` + `.json`, and `REPORT_DIR/{offsets.csv, summary.md,
offsets.png}`. A trial that cannot be aligned is set aside with its reason in offsets.csv.

Usage: `python -m pipeline.resample IN_DIR OUT_DIR REPORT_DIR [--params params.yaml]`.
"""

from __future__ import annotations

import csv
import json
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import typer
from scipy.ndimage import uniform_filter1d
from scipy.signal import butter, sosfiltfilt

from pipeline.config import ResampleParams, load_section

PHASES = ("rest", "insertion", "dwell", "retraction")
FORCES = ("fx", "fy", "fz")
ID_COLUMNS = ("batch_id", "trial_id", "angle_deg", "tissue_point", "t_s", "phase")
TRUTH_COLUMN = "sim_clock_offset_s"  # written by the simulator only; a lab's data has no truth
# A source counts as "faster than the grid" only above this margin: a 30.02 Hz host stream
# onto a 30 Hz grid has nothing to alias, and filtering it would only blur it.
FASTER_MARGIN = 1.05
CUTOFF_FRACTION = 0.8  # anti-alias cutoff as a fraction of the target Nyquist frequency
DIFF_SPAN_S = 0.1  # clock alignment compares changes over this span (see estimate_offset)
COARSE_STEP_S = 0.01  # first pass of the lag search (see estimate_offset)
OFFSET_CSV_COLUMNS = (
    "batch_id",
    "trial_id",
    "angle_deg",
    "offset_s",
    "quality",
    "true_offset_s",
    "error_s",
    "n_fsr",
    "n_ref",
    "n_grid",
    "n_dropped_gap",
    "status",
)


class SetAside(Exception):
    """A trial that cannot be aligned or resampled; the message is the reason."""


# --------------------------------------------------------------------------- units
def to_volts(values: np.ndarray, units: str, adc_bits: int | None, vref_v: float | None) -> np.ndarray:
    """Estimator samples in volts: ADC counts scale by vref / (2^bits - 1)."""
    values = np.asarray(values, dtype=np.float64)
    if units == "volts":
        return values
    if units == "counts":
        if adc_bits is None or vref_v is None:
            raise ValueError("units 'counts' need adc_bits and vref_v")
        return values * (float(vref_v) / (2 ** int(adc_bits) - 1))
    raise ValueError(f"unknown sensor units {units!r} (expected 'counts' or 'volts')")


def to_newtons(values: np.ndarray, units: str) -> np.ndarray:
    """Reference forces in N."""
    values = np.asarray(values, dtype=np.float64)
    if units == "N":
        return values
    if units == "mN":
        return values * 1e-3
    raise ValueError(f"unknown reference units {units!r} (expected 'N' or 'mN')")


# --------------------------------------------------------------------------- streams
def median_rate(t: np.ndarray) -> float:
    """Sample rate (Hz) of a stream from its median interval: robust to jitter and drops."""
    dt = np.diff(np.asarray(t, dtype=np.float64))
    dt = dt[dt > 0]
    if dt.size == 0:
        raise SetAside("stream has fewer than two distinct time stamps")
    return float(1.0 / np.median(dt))


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


# --------------------------------------------------------------------------- clock offset
@dataclass(frozen=True)
class OffsetEstimate:
    """Clock offset of one trial: reference stamp t_s happened at host time t_s + offset_s.

    `quality` is the explained variance (R², 0..1) of the reference forces' changes by the
    estimator channels' changes at the best lag; `lags_s`/`score` are the lags scored.
    """

    offset_s: float
    quality: float
    lags_s: np.ndarray = field(repr=False)
    score: np.ndarray = field(repr=False)
    on_edge: bool = False


def _channel_basis(volts: np.ndarray, span: int) -> np.ndarray:
    """Orthonormal basis of the (centred) regressors built from the channels' differences.

    Regressors per channel: its difference over `span` samples, and that difference times
    its (centred, scaled) level, so a linear fit can follow a sensitivity that changes along
    the FSR's saturating curve.
    """
    d = volts[span:] - volts[:-span]
    level = 0.5 * (volts[span:] + volts[:-span])
    level = level - level.mean(axis=0)
    scale = np.abs(level).max(axis=0)
    level = level / np.where(scale > 0, scale, 1.0)
    design = np.concatenate([d, d * level], axis=1)
    design = design - design.mean(axis=0)
    u, s, _ = np.linalg.svd(design, full_matrices=False)
    if s.size == 0 or s[0] <= 0:
        return u[:, :0]
    return u[:, s > s[0] * 1e-8]


def estimate_offset(
    t_fsr_s: np.ndarray,
    volts: np.ndarray,
    t_ref_s: np.ndarray,
    force_n: np.ndarray,
    max_offset_s: float,
    step_s: float,
    lowpass_order: int = 4,
) -> OffsetEstimate:
    """Clock offset that best explains the reference forces by the estimator channels.

    For every candidate lag L in [-max_offset_s, +max_offset_s] (step `step_s`) the
    reference is read at the estimator's own sample times (ref stamped t - L) and the
    changes of the three forces over ~0.1 s (DIFF_SPAN_S) are regressed (least squares, with
    intercept) on the changes of the channels (and those changes times the channel level,
    for the FSR's saturating curve). The score is the explained share of variance (R²).
    Differencing is the point: it makes the sharp events (contact, puncture drop, motion
    reversal, needle exit) dominate and removes most of what would bias a correlation of
    levels: the silicone's slow creep, drift, the preload. Regressing forces on channels
    makes the score blind to the channel count, the geometry and the signs, and the
    regressors stay the same at every lag, so a lag costs one projection. Lags are searched
    every COARSE_STEP_S, then every `step_s` around the best; the best lag is refined by a
    parabola through the score's peak. `lags_s`/`score` hold the lags actually scored.

    Raises SetAside when the streams overlap too little or the channels carry no signal.
    """
    t_fsr_s = np.asarray(t_fsr_s, dtype=np.float64)
    t_ref_s = np.asarray(t_ref_s, dtype=np.float64)
    volts = np.asarray(volts, dtype=np.float64).reshape(t_fsr_s.size, -1)
    force_n = np.asarray(force_n, dtype=np.float64).reshape(t_ref_s.size, -1)
    n_half = max(1, round(max_offset_s / step_s))

    fs_ref = median_rate(t_ref_s)
    fs_fsr = median_rate(t_fsr_s)
    if fs_ref > FASTER_MARGIN * fs_fsr:
        # A faster reference is low-passed to the estimator's band (zero phase: no bias),
        # so its noise does not swamp the differences; its sharp events stay sharp enough.
        force_n = lowpass(force_n, fs_ref, CUTOFF_FRACTION * 0.5 * fs_fsr, lowpass_order)
    # The reference on a fine uniform grid at the lag step: a lag is then a shift by whole
    # fine samples (exact: linear interpolation of a piecewise-linear signal).
    n_fine = math.floor((t_ref_s[-1] - t_ref_s[0]) / step_s) + 1
    fine = interp_columns(t_ref_s[0] + np.arange(n_fine) * step_s, t_ref_s, force_n)
    pos = (t_fsr_s - t_ref_s[0]) / step_s
    base = np.floor(pos).astype(np.int64)
    # Only estimator samples whose shifted time stays inside the reference for every lag:
    # every lag is then scored on the same samples, so scores compare fairly.
    inside = (base - n_half >= 0) & (base + n_half + 1 <= n_fine - 1)
    n_use = int(inside.sum())
    n_min = max(20, 4 * (2 * volts.shape[1] + 1))
    if n_use < n_min:
        raise SetAside(
            f"streams overlap too little to estimate the clock offset "
            f"({n_use} estimator samples within ±{max_offset_s:g} s of the reference; need {n_min})"
        )
    # Differences over ~DIFF_SPAN_S rather than one sample: on smooth stretches a one-sample
    # step is mostly sensor noise; on sharp events the longer span costs little.
    span = max(1, round(DIFF_SPAN_S * fs_fsr))
    if n_use <= span + n_min // 2:
        span = 1
    basis = _channel_basis(volts[inside], span)  # (n_use - span, q), columns orthogonal to 1
    if basis.shape[1] == 0:
        raise SetAside("estimator channels are constant: nothing to align the clocks on")
    base, frac = base[inside], pos[inside] - base[inside]

    # Coarse to fine: the score's peak is as wide as an estimator sample period or more, so
    # a search at a third of that (at most COARSE_STEP_S) cannot miss it; the full step is
    # then used around the best coarse lag.
    k = max(1, round(min(COARSE_STEP_S, 0.3 / fs_fsr) / step_s))
    coarse = np.unique(np.r_[np.arange(-n_half, n_half + 1, k), n_half])
    s_coarse = _lag_scores(coarse, base, frac, fine, basis, span)
    centre = int(coarse[np.argmax(s_coarse)])
    near = np.arange(max(-n_half, centre - 2 * k), min(n_half, centre + 2 * k) + 1)
    s_near = _lag_scores(near, base, frac, fine, basis, span)
    idx = np.r_[coarse, near]
    idx, first = np.unique(idx, return_index=True)
    lags, score = idx * step_s, np.r_[s_coarse, s_near][first]

    j = int(np.argmax(s_near))
    offset, peak = float(near[j] * step_s), float(s_near[j])
    on_edge = abs(int(near[j])) == n_half
    if 0 < j < near.size - 1:
        y0, y1, y2 = s_near[j - 1], s_near[j], s_near[j + 1]
        curvature = y0 - 2 * y1 + y2
        if curvature < 0:
            delta = 0.5 * (y0 - y2) / curvature
            offset += float(np.clip(delta, -1, 1)) * step_s
            peak = float(y1 - 0.25 * (y0 - y2) * delta)
    return OffsetEstimate(offset, float(np.clip(peak, 0, 1)), lags, score, on_edge)


def _lag_scores(
    lag_idx: np.ndarray, base: np.ndarray, frac: np.ndarray, fine: np.ndarray, basis: np.ndarray, span: int
) -> np.ndarray:
    """R² of the reference changes explained by the channel basis, at lags `lag_idx` (fine steps).

    The reference at estimator sample i and lag l is `fine` at position base_i + frac_i - l.
    Plain einsum loops, not BLAS: they stay fast when other processes hold the cores.
    """
    out = np.empty(lag_idx.size)
    chunk = max(1, 3_000_000 // (3 * base.size))  # bounded memory for long trials
    for a in range(0, lag_idx.size, chunk):
        lags = lag_idx[a : a + chunk]
        j = base[:, None] - lags[None, :]  # (n, lags)
        y = fine[j] + frac[:, None, None] * (fine[j + 1] - fine[j])  # (n, lags, 3)
        dy = y[span:] - y[:-span]
        dy -= dy.mean(axis=0)
        total = np.einsum("nlk,nlk->l", dy, dy)
        proj = np.einsum("nq,nlk->qlk", basis, dy)
        explained = np.einsum("qlk,qlk->l", proj, proj)
        out[a : a + chunk] = np.where(total > 0, explained / np.where(total > 0, total, 1.0), 0.0)
    return out


# --------------------------------------------------------------------------- phases
def label_phases(force_n: np.ndarray, rate_hz: float) -> np.ndarray:
    """Phase of every sample of one trial's reference force (n, 3) on a uniform grid.

    The rule, all on the force projected on its principal direction p(t):
    - rest baseline: median of the quieter of the first/last 0.5 s; p = (F - base) . u with u
      the first principal axis of F - base, signed so the first departure from rest is > 0;
    - noise sigma: MAD of the first differences / sqrt(2); p is smoothed over 0.2 s;
      "active" means |p| > thr = max(6 sigma, 5 % of max |p|);
    - insertion starts where p, walking back from the first active sample, last was within
      2 noise levels (of the smoothed p) of rest;
    - retraction starts at the onset of the fall into the pull (first p < -thr after the
      maximum; without a pull, the last fall back to rest): walking back from there while
      p still falls faster than a quarter of that fall's steepest rate;
    - dwell: walking back from the retraction start while p does not rise (slope below a
      noise-based threshold): the robot stopped, the tissue holds or relaxes; may be empty;
    - the retraction ends at the needle exit: after the deepest pull, where p has come half
      way back to rest (without a pull: at the end of activity); rest after that.
    No activity at all gives "rest" throughout. Phases always come in the order
    rest -> insertion -> dwell -> retraction -> rest, any of them possibly empty.
    """
    force_n = np.asarray(force_n, dtype=np.float64)
    n = force_n.shape[0]
    labels = np.full(n, PHASES[0], dtype=object)
    if n < 5:
        return labels
    edge = max(3, round(0.5 * rate_hz))
    ends = [force_n[:edge], force_n[-edge:]]
    quiet = min(ends, key=lambda seg: float(np.linalg.norm(seg - np.median(seg, axis=0), axis=1).mean()))
    f = force_n - np.median(quiet, axis=0)
    _, _, vt = np.linalg.svd(f, full_matrices=False)
    p = f @ vt[0]

    d = np.diff(p)
    sigma = 1.4826 * float(np.median(np.abs(d - np.median(d)))) / math.sqrt(2)
    win = max(1, round(0.2 * rate_hz))
    ps = uniform_filter1d(p, win, mode="nearest")
    amp = float(np.abs(ps).max())
    thr = max(6 * sigma, 0.05 * amp)
    if amp == 0 or amp <= thr or not np.isfinite(amp):
        return labels
    active = np.flatnonzero(np.abs(ps) > thr)
    first = int(active[0])
    if ps[first] < 0:
        p, ps = -p, -ps
    sigma_s = sigma / math.sqrt(win)

    # Insertion start: back from the first active sample to the last one near rest.
    start = first
    while start > 0 and ps[start - 1] > 2 * sigma_s:
        start -= 1

    slope = np.gradient(ps) * rate_hz  # N/s
    # slope noise of a moving average then central difference of white noise
    slope_noise = sigma * rate_hz / win
    peak = first + int(np.argmax(ps[first:]))
    neg = np.flatnonzero(ps[peak:] < -thr)
    pulled = neg.size > 0
    anchor = peak + int(neg[0]) if pulled else int(active[-1])

    # Retraction start: onset of the fall that ends at the anchor. Only the descent that
    # runs into the anchor counts (a puncture drop earlier on can be steeper).
    lo = anchor
    while lo > peak and slope[lo - 1] < 0:
        lo -= 1
    i_steep = lo + int(np.argmin(slope[lo : anchor + 1]))
    fall_rate = float(-slope[i_steep])
    r_start = i_steep
    if fall_rate > 0:
        limit = max(0.25 * fall_rate, 3 * slope_noise)
        while r_start > lo and -slope[r_start - 1] > limit:
            r_start -= 1
    r_start = max(r_start, start)

    # Dwell: back from the retraction start while the force does not rise.
    d_start = r_start
    rise = 3 * slope_noise
    while d_start > start and slope[d_start - 1] < rise and ps[d_start - 1] > thr:
        d_start -= 1

    # Needle exit: half way back from the deepest pull (or the end of activity).
    if pulled:
        i_min = r_start + int(np.argmin(ps[r_start:]))
        back = np.flatnonzero(ps[i_min:] > 0.5 * ps[i_min])
        exit_ = i_min + int(back[0]) if back.size else n
    else:
        exit_ = int(active[-1]) + 1
    exit_ = max(exit_, r_start)

    labels[start:d_start] = "insertion"
    labels[d_start:r_start] = "dwell"
    labels[r_start:exit_] = "retraction"
    return labels


# --------------------------------------------------------------------------- one trial
@dataclass
class ResampledTrial:
    """One trial on the common grid (host time base; `t_s` starts at 0)."""

    offset: OffsetEstimate
    t0_host_s: float  # host time of grid point t_s = 0
    t_s: np.ndarray
    volts: np.ndarray  # (n, channels)
    force_n: np.ndarray  # (n, 3)
    phase: np.ndarray
    n_dropped_gap: int


def resample_trial(
    t_fsr_s: np.ndarray,
    volts: np.ndarray,
    t_ref_s: np.ndarray,
    force_n: np.ndarray,
    p: ResampleParams,
) -> ResampledTrial:
    """Align, resample and label one trial (inputs already in s, V and N). Raises SetAside."""
    if t_fsr_s.size < 2 or t_ref_s.size < 2:
        raise SetAside("a stream has fewer than two samples")
    if not (np.all(np.isfinite(volts)) and np.all(np.isfinite(force_n))):
        raise SetAside("missing (NaN) or infinite values in a stream")
    est = estimate_offset(t_fsr_s, volts, t_ref_s, force_n, p.max_offset_s, p.offset_step_s, p.lowpass_order)
    if est.on_edge:
        raise SetAside(
            f"clock offset at the edge of the ±{p.max_offset_s:g} s search window "
            f"(quality {est.quality:.2f}): the true offset is probably outside it"
        )
    t_ref_host = t_ref_s + est.offset_s
    lo, hi = max(t_fsr_s[0], t_ref_host[0]), min(t_fsr_s[-1], t_ref_host[-1])
    # The grid is anchored to the estimator's own uniform grid, so that at equal rates its
    # (quantised, noisy) samples are copied, not blurred by interpolation.
    fsr_rate = median_rate(t_fsr_s)
    k0 = math.ceil((lo - t_fsr_s[0]) * fsr_rate - 1e-6)
    t0 = t_fsr_s[0] + k0 / fsr_rate
    n = math.floor((hi - t0) * p.rate_hz + 1e-6) + 1 if hi >= t0 else 0
    if n < 10:
        raise SetAside(f"streams overlap for only {max(hi - lo, 0):.2f} s after clock alignment")
    k = np.arange(n)
    grid = t0 + k / p.rate_hz
    v = resample_stream(t_fsr_s, volts, grid, p.rate_hz, p.lowpass_order)
    f = resample_stream(t_ref_host, force_n, grid, p.rate_hz, p.lowpass_order)
    # Phases on the full grid (uniform spacing is what the smoothing assumes), gaps dropped after.
    phase = label_phases(f, p.rate_hz)
    keep = ~(gap_mask(t_fsr_s, grid, p.max_gap_s) | gap_mask(t_ref_host, grid, p.max_gap_s))
    if keep.sum() < 10:
        raise SetAside("fewer than 10 grid points left outside gaps")
    return ResampledTrial(
        offset=est,
        t0_host_s=float(t0),
        t_s=k[keep] / p.rate_hz,
        volts=v[keep],
        force_n=f[keep],
        phase=phase[keep],
        n_dropped_gap=int((~keep).sum()),
    )


# --------------------------------------------------------------------------- one batch
@dataclass(frozen=True)
class BatchInfo:
    """What the stage needs from an ingested batch's batch.json."""

    batch_id: str
    unit_id: str
    channels: tuple[str, ...]
    units: str
    adc_bits: int | None
    vref_v: float | None
    ref_units: str

    @classmethod
    def from_json(cls, meta: dict[str, Any]) -> BatchInfo:
        s, r = meta["sensor"], meta["reference"]
        return cls(
            batch_id=str(meta["batch_id"]),
            unit_id=str(s["unit_id"]),
            channels=tuple(str(c) for c in s["channels"]),
            units=str(s["units"]),
            adc_bits=None if s.get("adc_bits") is None else int(s["adc_bits"]),
            vref_v=None if s.get("vref_v") is None else float(s["vref_v"]),
            ref_units=str(r["units"]),
        )


def output_schema(channels: tuple[str, ...] | list[str]) -> pa.Schema:
    """Arrow schema of a resampled batch file (shared with `split`)."""
    fields = [
        pa.field("batch_id", pa.string()),
        pa.field("trial_id", pa.string()),
        pa.field("angle_deg", pa.float64()),
        pa.field("tissue_point", pa.string()),
        pa.field("t_s", pa.float64()),
        pa.field("phase", pa.string()),
    ]
    fields += [pa.field(c, pa.float64()) for c in channels]
    fields += [pa.field(c, pa.float64()) for c in FORCES]
    return pa.schema(fields)


def write_table(table: pa.Table, path: Path) -> None:
    """Parquet with fixed settings and no pandas metadata, so equal data give equal bytes."""
    path.parent.mkdir(parents=True, exist_ok=True)
    pq.write_table(table.replace_schema_metadata(None), path, compression="zstd")


def batch_dirs(in_dir: Path) -> list[Path]:
    """Accepted ingested batches: visible sub-folders holding trials.parquet, sorted by name.

    Ingest leaves set-aside batches without trials.parquet and writes through `.staging/`.
    """
    if not in_dir.is_dir():
        return []
    return sorted(
        p
        for p in in_dir.iterdir()
        if p.is_dir() and not p.name.startswith(".") and (p / "trials.parquet").is_file()
    )


def _by_trial(df: pd.DataFrame, time_col: str) -> dict[str, pd.DataFrame]:
    df = df.sort_values(["trial_id", time_col], kind="stable")
    return {str(k): g for k, g in df.groupby("trial_id", sort=True)}


def _clean_time(t: np.ndarray, *arrays: np.ndarray) -> tuple[np.ndarray, ...]:
    """Drop repeated time stamps (keep the first), so every stream is strictly increasing."""
    keep = np.ones(t.size, dtype=bool)
    keep[1:] = np.diff(t) > 0
    return (t[keep], *(a[keep] for a in arrays))


def _num(x: float | None, fmt: str = ".6f") -> str:
    return "" if x is None or not np.isfinite(x) else format(x, fmt)


def process_batch(batch_dir: Path, p: ResampleParams) -> tuple[BatchInfo, pa.Table, list[dict[str, Any]]]:
    """Resample every trial of one ingested batch; returns its info, table and offsets.csv rows."""
    info = BatchInfo.from_json(json.loads((batch_dir / "batch.json").read_text()))
    trials = pd.read_parquet(batch_dir / "trials.parquet")
    fsr = _by_trial(pd.read_parquet(batch_dir / "fsr.parquet"), "t_ms")
    ref = _by_trial(pd.read_parquet(batch_dir / "ref.parquet"), "t_s")
    columns: dict[str, list[np.ndarray]] = {name: [] for name in output_schema(info.channels).names}
    rows: list[dict[str, Any]] = []
    trials = trials.assign(trial_id=trials["trial_id"].astype(str)).sort_values("trial_id", kind="stable")
    for trial in trials.to_dict("records"):
        tid = str(trial["trial_id"])
        truth = _truth(trial.get(TRUTH_COLUMN))
        row: dict[str, Any] = {
            "batch_id": info.batch_id,
            "trial_id": tid,
            "angle_deg": f"{float(trial['angle_deg']):g}",
            "offset_s": "",
            "quality": "",
            "true_offset_s": _num(truth),
            "error_s": "",
            "n_fsr": 0,
            "n_ref": 0,
            "n_grid": 0,
            "n_dropped_gap": 0,
            "status": "ok",
        }
        rows.append(row)
        try:
            if tid not in fsr or tid not in ref:
                raise SetAside("no estimator or no reference samples for this trial")
            fs, rf = fsr[tid], ref[tid]
            row["n_fsr"], row["n_ref"] = len(fs), len(rf)
            t_fsr, volts = _clean_time(
                fs["t_ms"].to_numpy(np.float64) / 1000.0,
                to_volts(
                    fs[list(info.channels)].to_numpy(np.float64), info.units, info.adc_bits, info.vref_v
                ),
            )
            t_ref, force = _clean_time(
                rf["t_s"].to_numpy(np.float64),
                to_newtons(rf[list(FORCES)].to_numpy(np.float64), info.ref_units),
            )
            res = resample_trial(t_fsr, volts, t_ref, force, p)
        except SetAside as e:
            row["status"] = f"set aside: {e}"
            continue
        except KeyError as e:
            row["status"] = f"set aside: missing column {e}"
            continue
        row["offset_s"] = _num(res.offset.offset_s)
        row["quality"] = _num(res.offset.quality, ".4f")
        if truth is not None:
            row["error_s"] = _num(res.offset.offset_s - truth)
        row["n_grid"], row["n_dropped_gap"] = res.t_s.size, res.n_dropped_gap
        n = res.t_s.size
        columns["batch_id"].append(np.full(n, info.batch_id, dtype=object))
        columns["trial_id"].append(np.full(n, tid, dtype=object))
        columns["angle_deg"].append(np.full(n, float(trial["angle_deg"])))
        columns["tissue_point"].append(np.full(n, str(trial["tissue_point"]), dtype=object))
        columns["t_s"].append(res.t_s)
        columns["phase"].append(res.phase)
        for j, c in enumerate(info.channels):
            columns[c].append(res.volts[:, j])
        for j, c in enumerate(FORCES):
            columns[c].append(res.force_n[:, j])
    schema = output_schema(info.channels)
    arrays = [
        pa.array(np.concatenate(columns[f.name]) if columns[f.name] else [], type=f.type) for f in schema
    ]
    return info, pa.Table.from_arrays(arrays, schema=schema), rows


def _truth(value: Any) -> float | None:
    """The simulator's true offset, when the trials table carries one."""
    if value is None:
        return None
    try:
        x = float(value)
    except (TypeError, ValueError):
        return None
    return x if np.isfinite(x) else None


# --------------------------------------------------------------------------- reports
def write_offsets_csv(rows: list[dict[str, Any]], path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=OFFSET_CSV_COLUMNS, lineterminator="\n")
        w.writeheader()
        w.writerows(rows)


def phase_durations(table: pa.Table, rate_hz: float) -> pd.DataFrame:
    """Seconds of each phase per trial (rows: batch_id, trial_id; columns: PHASES)."""
    if table.num_rows == 0:
        return pd.DataFrame(columns=list(PHASES), dtype=float)
    df = table.select(["batch_id", "trial_id", "phase"]).to_pandas()
    counts = df.groupby(["batch_id", "trial_id", "phase"]).size().unstack(fill_value=0)
    return counts.reindex(columns=list(PHASES), fill_value=0) / rate_hz


def summary_markdown(rows: list[dict[str, Any]], durations: pd.DataFrame, p: ResampleParams) -> str:
    """Counts, offset error against the truth (when known) and phase durations."""
    ok = [r for r in rows if r["status"] == "ok"]
    aside = [r for r in rows if r["status"] != "ok"]
    lines = [
        "# Resample report",
        "",
        f"Grid {p.rate_hz:g} Hz; offset search ±{p.max_offset_s:g} s in {p.offset_step_s * 1e3:g} ms steps; "
        f"grid points in gaps > {p.max_gap_s:g} s dropped.",
        "",
        f"- trials: {len(rows)} ({len(ok)} ok, {len(aside)} set aside)",
        f"- batches: {len({r['batch_id'] for r in rows})}",
        f"- grid samples written: {sum(int(r['n_grid']) for r in ok)}; "
        f"dropped in gaps: {sum(int(r['n_dropped_gap']) for r in ok)}",
    ]
    if ok:
        q = np.array([float(r["quality"]) for r in ok])
        off = np.array([float(r["offset_s"]) for r in ok])
        lines.append(
            f"- estimated offsets: median {np.median(off) * 1e3:.1f} ms, range "
            f"[{off.min() * 1e3:.1f}, {off.max() * 1e3:.1f}] ms; quality (R²) median {np.median(q):.3f}, "
            f"min {q.min():.3f}"
        )
    err = np.array([float(r["error_s"]) for r in ok if r["error_s"] != ""])
    if err.size:
        a = np.abs(err) * 1e3
        period = 1e3 / p.rate_hz
        lines += [
            "",
            "## Offset error against the simulator's truth",
            "",
            "| trials | bias (ms) | median abs (ms) | p95 abs (ms) | max abs (ms) | within one grid period |",
            "|---|---|---|---|---|---|",
            f"| {err.size} | {err.mean() * 1e3:+.1f} | {np.median(a):.1f} | {np.percentile(a, 95):.1f} | "
            f"{a.max():.1f} | {np.mean(a <= period) * 100:.1f} % |",
        ]
    if len(durations):
        lines += [
            "",
            "## Phase durations (s per trial)",
            "",
            "| phase | median | min | max | trials with it |",
            "|---|---|---|---|---|",
        ]
        for ph in PHASES:
            col = durations[ph]
            lines.append(
                f"| {ph} | {col.median():.2f} | {col.min():.2f} | {col.max():.2f} | {int((col > 0).sum())} |"
            )
    if aside:
        lines += ["", "## Set aside", ""]
        lines += [
            f"- {r['batch_id']} / {r['trial_id']}: {r['status'].removeprefix('set aside: ')}" for r in aside
        ]
    return "\n".join(lines) + "\n"


def plot_offsets(rows: list[dict[str, Any]], path: Path, period_s: float) -> None:
    """Offset error against the truth when it is known, else the estimates and their quality."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ok = [r for r in rows if r["status"] == "ok"]
    known = [r for r in ok if r["true_offset_s"] != ""]
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.2))
    if known:
        truth = np.array([float(r["true_offset_s"]) for r in known]) * 1e3
        err = np.array([float(r["error_s"]) for r in known]) * 1e3
        angle = np.array([float(r["angle_deg"]) for r in known])
        band = period_s * 1e3
        axes[0].axhspan(-band, band, color="0.92", label=f"± one grid period ({band:.0f} ms)")
        sc = axes[0].scatter(truth, err, c=angle, s=12, cmap="viridis")
        fig.colorbar(sc, ax=axes[0], label="angle (deg)")
        axes[0].axhline(0, color="0.5", lw=0.8)
        axes[0].set(xlabel="true offset (ms)", ylabel="estimate - truth (ms)", title="Offset error per trial")
        axes[0].legend(loc="upper left", fontsize=8)
        axes[1].hist(err, bins=40)
        axes[1].axvline(0, color="0.5", lw=0.8)
        axes[1].set(xlabel="estimate - truth (ms)", ylabel="trials", title="Offset error")
    else:
        est = np.array([float(r["offset_s"]) for r in ok]) * 1e3
        quality = np.array([float(r["quality"]) for r in ok])
        axes[0].hist(est, bins=40)
        axes[0].set(xlabel="estimated clock offset (ms)", ylabel="trials", title="Clock offset per trial")
        axes[1].hist(quality, bins=40, range=(0, 1))
        axes[1].set(xlabel="alignment quality (R² of force changes)", ylabel="trials", title="Fit quality")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100, metadata={"Software": None})
    plt.close(fig)


PHASE_COLOURS = {"insertion": "#d8ecd8", "dwell": "#fbeccb", "retraction": "#f6d5d5"}


def plot_example_trials(out_dir: Path, path: Path) -> None:
    """One aligned trial per angle: the channels (V) above the reference force (N), phases shaded."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    examples = []
    for file in sorted(out_dir.glob("*.parquet")):
        frame = pd.read_parquet(file)
        channels = json.loads(file.with_suffix(".json").read_text())["channels"]
        for angle, group in frame.groupby("angle_deg", sort=True):
            if angle not in [a for a, *_ in examples]:
                first = group[group.trial_id == group.trial_id.min()]
                examples.append((angle, first, channels))
    if not examples:
        return
    examples.sort(key=lambda e: e[0])
    fig, axes = plt.subplots(2, len(examples), figsize=(3.2 * len(examples), 5.5), sharex=True, squeeze=False)
    for col, (angle, trial, channels) in enumerate(examples):
        t = trial.t_s.to_numpy()
        for row in (0, 1):
            ax = axes[row, col]
            changes = np.flatnonzero(trial.phase.to_numpy()[1:] != trial.phase.to_numpy()[:-1]) + 1
            for start, stop in zip(np.r_[0, changes], np.r_[changes, len(t)], strict=True):
                colour = PHASE_COLOURS.get(trial.phase.iloc[start])
                if colour:
                    ax.axvspan(t[start], t[min(stop, len(t) - 1)], color=colour, lw=0)
        for c in channels:
            axes[0, col].plot(t, trial[c], lw=1, label=c)
        for axis in ("fx", "fy", "fz"):
            axes[1, col].plot(t, trial[axis], lw=1, label=axis)
        axes[0, col].set_title(f"{angle:g}° — {trial.batch_id.iloc[0]}/{trial.trial_id.iloc[0]}", fontsize=9)
        axes[1, col].set_xlabel("t (s)")
    axes[0, 0].set_ylabel("estimator (V)")
    axes[1, 0].set_ylabel("reference force (N)")
    axes[0, -1].legend(fontsize=7, loc="upper right")
    handles = [plt.Rectangle((0, 0), 1, 1, color=c) for c in PHASE_COLOURS.values()]
    axes[1, -1].legend([*axes[1, -1].get_lines(), *handles], ["fx", "fy", "fz", *PHASE_COLOURS], fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=90, metadata={"Software": None})
    plt.close(fig)


# --------------------------------------------------------------------------- stage
def run(in_dir: Path, out_dir: Path, report_dir: Path, p: ResampleParams) -> list[dict[str, Any]]:
    """Resample every accepted batch, write outputs and reports; return the offsets.csv rows."""
    out_dir.mkdir(parents=True, exist_ok=True)
    written: set[str] = set()
    all_rows: list[dict[str, Any]] = []
    durations: list[pd.DataFrame] = []
    for batch_dir in batch_dirs(in_dir):
        info, table, rows = process_batch(batch_dir, p)
        write_table(table, out_dir / f"{info.batch_id}.parquet")
        meta = {
            "batch_id": info.batch_id,
            "channels": list(info.channels),
            "rate_hz": p.rate_hz,
            "unit_id": info.unit_id,
        }
        (out_dir / f"{info.batch_id}.json").write_text(json.dumps(meta, indent=2, sort_keys=True) + "\n")
        written |= {f"{info.batch_id}.parquet", f"{info.batch_id}.json"}
        all_rows += rows
        durations.append(phase_durations(table, p.rate_hz))
        n_ok = sum(r["status"] == "ok" for r in rows)
        errs = [abs(float(r["error_s"])) for r in rows if r["error_s"] != ""]
        err_txt = f", offset error median {np.median(errs) * 1e3:.1f} ms" if errs else ""
        print(
            f"resample: {info.batch_id}: {n_ok}/{len(rows)} trials ok, "
            f"{table.num_rows} grid samples{err_txt}",
            file=sys.stderr,
        )
    # Files of batches that are gone would otherwise be picked up by `split`.
    for stale in sorted(out_dir.glob("*")):
        if stale.is_file() and stale.suffix in (".parquet", ".json") and stale.name not in written:
            stale.unlink()
    report_dir.mkdir(parents=True, exist_ok=True)
    write_offsets_csv(all_rows, report_dir / "offsets.csv")
    dur = pd.concat(durations) if durations else pd.DataFrame(columns=list(PHASES), dtype=float)
    (report_dir / "summary.md").write_text(summary_markdown(all_rows, dur, p))
    plot_offsets(all_rows, report_dir / "offsets.png", 1.0 / p.rate_hz)
    plot_example_trials(out_dir, report_dir / "trials.png")
    return all_rows


def main(in_dir: Path, out_dir: Path, report_dir: Path, params: Path = Path("params.yaml")) -> None:
    """Align the clocks and resample every ingested batch onto the common grid."""
    run(in_dir, out_dir, report_dir, load_section(ResampleParams, "resample", params))


if __name__ == "__main__":
    typer.run(main)
