"""Estimating the clock offset between a trial's two streams from the signals themselves, never
from the two t=0 (`docs/rig-log-format.md`, "Units and clocks"): the lag at which the estimator
channels' changes best explain the reference forces' changes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from pipeline.signals.filters import (
    CUTOFF_FRACTION,
    FASTER_MARGIN,
    SetAside,
    interp_columns,
    lowpass,
    median_rate,
)

DIFF_SPAN_S = 0.1  # clock alignment compares changes over this span (see estimate_offset)
COARSE_STEP_S = 0.01  # first pass of the lag search (see estimate_offset)


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
    *,
    shared_clock: bool = False,
    memo: dict | None = None,
) -> OffsetEstimate:
    """Clock offset that best explains the reference forces by the estimator channels.

    With `shared_clock` (batch.yaml `reference.clock: shared`: both streams were stamped by one
    clock) no offset is searched: the offset is 0 and `quality` is the score at lag 0.

    For every candidate lag L in [-max_offset_s, +max_offset_s] (step `step_s`) the
    reference is read at the estimator's own sample times (ref stamped t - L) and the
    changes of the forces (each axis the reference records) over ~0.1 s (DIFF_SPAN_S) are
    regressed (least squares, with intercept) on the changes of the channels (and those
    changes times the channel level, for the FSR's saturating curve). The score is the
    explained share of variance (R²).
    Differencing is the point: it makes the sharp events (contact, puncture drop, motion
    reversal, needle exit) dominate and removes most of what would bias a correlation of
    levels: the silicone's slow creep, drift, the preload. Regressing forces on channels
    makes the score blind to the channel count, the geometry and the signs, and the
    regressors stay the same at every lag, so a lag costs one projection. Lags are searched
    every COARSE_STEP_S, then every `step_s` around the best; the best lag is refined by a
    parabola through the score's peak. `lags_s`/`score` hold the lags actually scored.

    `memo`: a dict the caller passes to every call on the same estimator stream (`t_fsr_s`, `volts`)
    and reference forces (`force_n`), their stamps shifted (`trial.wider`): the estimator's rate and
    the low-passed reference are computed once, the same values as computed anew.

    Raises SetAside when the streams overlap too little or the channels carry no signal.
    """
    t_fsr_s = np.asarray(t_fsr_s, dtype=np.float64)
    t_ref_s = np.asarray(t_ref_s, dtype=np.float64)
    volts = np.asarray(volts, dtype=np.float64).reshape(t_fsr_s.size, -1)
    force_n = np.asarray(force_n, dtype=np.float64).reshape(t_ref_s.size, -1)
    n_half = 0 if shared_clock else max(1, round(max_offset_s / step_s))

    memo = {} if memo is None else memo
    fs_ref = median_rate(t_ref_s)
    if "fs_fsr" not in memo:
        memo["fs_fsr"] = median_rate(t_fsr_s)
    fs_fsr = memo["fs_fsr"]
    if fs_ref > FASTER_MARGIN * fs_fsr:
        # A faster reference is low-passed to the estimator's band (zero phase: no bias),
        # so its noise does not swamp the differences; its sharp events stay sharp enough.
        # (Keyed by the exact rates: a shifted copy of the stamps may give a rate a bit apart.)
        key = ("lowpass", fs_ref, fs_fsr, lowpass_order)
        if key not in memo:
            memo[key] = lowpass(force_n, fs_ref, CUTOFF_FRACTION * 0.5 * fs_fsr, lowpass_order)
        force_n = memo[key]
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
            f"streams overlap too little to estimate the clock offset ({n_use} estimator samples within "
            f"±{0 if shared_clock else max_offset_s:g} s of the reference; need {n_min}): the estimator is "
            f"stamped {t_fsr_s[0]:.2f} to {t_fsr_s[-1]:.2f} s, the reference {t_ref_s[0]:.2f} to "
            f"{t_ref_s[-1]:.2f} s; a reference from another recording?"
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
    # one clock (lag 0 only, as `trial.wider` asks ~500 times per low-quality trial): nothing finer to score
    same = np.array_equal(near, coarse)
    s_near = s_coarse if same else _lag_scores(near, base, frac, fine, basis, span)
    idx = np.r_[coarse, near]
    idx, first = np.unique(idx, return_index=True)
    lags, score = idx * step_s, np.r_[s_coarse, s_near][first]

    j = int(np.argmax(s_near))
    offset, peak = float(near[j] * step_s), float(s_near[j])
    on_edge = not shared_clock and abs(int(near[j])) == n_half
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
        y = fine[j] + frac[:, None, None] * (fine[j + 1] - fine[j])  # (n, lags, axes)
        dy = y[span:] - y[:-span]
        dy -= dy.mean(axis=0)
        total = np.einsum("nlk,nlk->l", dy, dy)
        proj = np.einsum("nq,nlk->qlk", basis, dy)
        explained = np.einsum("qlk,qlk->l", proj, proj)
        out[a : a + chunk] = np.where(total > 0, explained / np.where(total > 0, total, 1.0), 0.0)
    return out
