"""One trial's two streams on the common grid, in memory: checked for a response, their clocks
aligned (`pipeline.signals.clock`), put on one uniform grid at `resample.rate_hz` over their overlap
(`pipeline.signals.filters`) and every grid sample given a phase (`pipeline.signals.phases`)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from pipeline.config import ResampleParams
from pipeline.signals import pairing
from pipeline.signals.clock import OffsetEstimate, estimate_offset
from pipeline.signals.filters import SetAside, gap_mask, median_rate, resample_stream
from pipeline.signals.phases import label_phases

WIDE_STEP_S = 0.02  # offsets tried when a trial's own reference is searched wider (see wider)


@dataclass
class ResampledTrial:
    """One trial on the common grid (host time base; `t_s` starts at 0)."""

    offset: OffsetEstimate
    t0_host_s: float  # host time of grid point t_s = 0
    t_s: np.ndarray
    volts: np.ndarray  # (n, channels)
    force_n: np.ndarray  # (n, axes): the batch's recorded axes (resample.BatchInfo.axes)
    phase: np.ndarray
    n_dropped_gap: int


@dataclass(frozen=True)
class Streams:
    """One trial's two streams, in s, V and N, each strictly increasing in time."""

    t_fsr_s: np.ndarray
    volts: np.ndarray  # (n, channels)
    t_ref_s: np.ndarray
    force_n: np.ndarray  # (m, axes): the axes the reference records, one to three


# An estimator that moves less than this (about two counts of a 10-bit, 5 V ADC) while the reference
# force spans more than this has not recorded the insertion: stuck, dead or unpowered. Any design
# that can sense a needle moves its volts far more over an insertion.
STILL_V = 0.01
MOVED_N = 0.2


def check_response(streams: Streams, channels: tuple[str, ...] | None = None) -> None:
    """SetAside, with that reason, when the estimator, or one of its channels, did not respond to an
    insertion the reference recorded: before the clock alignment, which would blame the clocks. A
    channel is stuck when it moves less than STILL_V while another moves ten times that."""
    if streams.volts.size == 0 or streams.force_n.size == 0:
        return
    moved = np.ptp(streams.volts, axis=0)
    span_n = float(np.max(np.ptp(streams.force_n, axis=0)))
    if span_n < MOVED_N:
        return
    if float(moved.max()) < STILL_V:
        raise SetAside(
            f"the estimator does not respond: its channels move at most {1000 * moved.max():.1f} mV "
            f"while the reference force spans {span_n:.2f} N (stuck at rest, dead or unpowered?)"
        )
    names = channels or tuple(f"channel {k + 1}" for k in range(len(moved)))
    still = moved < STILL_V
    if still.any() and moved.max() >= 10 * STILL_V:
        stuck = [n for n, s in zip(names, still, strict=True) if s]
        raise SetAside(
            f"{', '.join(stuck)} does not respond: moves at most {1000 * moved[still].max():.1f} mV while "
            f"another channel moves {1000 * moved.max():.0f} mV and the reference force spans "
            f"{span_n:.2f} N (a stuck channel)"
        )


def align(fsr: Streams, ref: Streams, p: ResampleParams, *, shared_clock: bool = False) -> OffsetEstimate:
    """The clock offset between `fsr`'s estimator stream and `ref`'s reference stream (usually one
    trial's; another trial's when checking a pairing). Raises SetAside when they cannot be aligned;
    the quality is judged by the caller."""
    if fsr.t_fsr_s.size < 2 or ref.t_ref_s.size < 2:
        raise SetAside("a stream has fewer than two samples")
    if not (np.all(np.isfinite(fsr.volts)) and np.all(np.isfinite(ref.force_n))):
        raise SetAside("missing (NaN) or infinite values in a stream")
    est = estimate_offset(
        fsr.t_fsr_s,
        fsr.volts,
        ref.t_ref_s,
        ref.force_n,
        p.max_offset_s,
        p.offset_step_s,
        p.lowpass_order,
        shared_clock=shared_clock,
    )
    if est.on_edge:
        shift = wider(Streams(fsr.t_fsr_s, fsr.volts, ref.t_ref_s, ref.force_n), p)
        if shift is not None and pairing.is_shift(shift):
            raise SetAside(pairing.shifted(shift, shared=shared_clock))
        raise SetAside(
            f"clock offset at the edge of the ±{p.max_offset_s:g} s search window "
            f"(quality {est.quality:.2f}): the true offset is probably outside it"
        )
    return est


def wider(streams: Streams, p: ResampleParams) -> pairing.Shift | None:
    """A trial's own reference tried at offsets up to `pairing.WIDE_FACTOR` times the search window,
    every `WIDE_STEP_S`, each scored on the samples the two streams share at that offset (at least
    half the estimator's): the best quality inside the window and outside it. None: no offset
    outside the window leaves enough overlap."""
    window = pairing.WIDE_FACTOR * p.max_offset_s
    lags = np.arange(-window, window + WIDE_STEP_S / 2, WIDE_STEP_S)
    scores = np.full(lags.size, np.nan)
    t_fsr = streams.t_fsr_s
    memo: dict = {}  # the same streams at every lag: their rates and low-passed forces once
    for i, lag in enumerate(lags):
        t_ref = streams.t_ref_s + lag
        if np.mean((t_fsr >= t_ref[0]) & (t_fsr <= t_ref[-1])) < 0.5:
            continue
        try:
            scores[i] = estimate_offset(
                t_fsr,
                streams.volts,
                t_ref,
                streams.force_n,
                0.0,
                p.offset_step_s,
                p.lowpass_order,
                shared_clock=True,
                memo=memo,
            ).quality
        except SetAside:
            continue
    inner = np.abs(lags) <= p.max_offset_s + 1e-9
    if np.all(np.isnan(scores[~inner])) or np.all(np.isnan(scores[inner])):
        return None
    best = int(np.nanargmax(np.where(inner, np.nan, scores)))
    return pairing.Shift(
        float(lags[best]), float(scores[best]), float(np.nanmax(scores[inner])), p.max_offset_s
    )


def on_grid(streams: Streams, est: OffsetEstimate, p: ResampleParams) -> ResampledTrial:
    """One aligned trial put on the common grid and labelled. Raises SetAside."""
    t_fsr_s, volts, t_ref_s, force_n = streams.t_fsr_s, streams.volts, streams.t_ref_s, streams.force_n
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


def estimator_only(
    t_fsr_s: np.ndarray, volts: np.ndarray, p: ResampleParams
) -> tuple[np.ndarray, np.ndarray]:
    """An estimator stream alone on the common grid (t_s from 0 at its first sample, gaps dropped):
    what a trial whose reference cannot be aligned still gives to a replay. Raises SetAside."""
    t, v = clean_time(np.asarray(t_fsr_s, dtype=np.float64), np.asarray(volts, dtype=np.float64))
    if t.size < 2 or not np.all(np.isfinite(v)):
        raise SetAside("the estimator stream has fewer than two samples or missing values")
    n = math.floor((t[-1] - t[0]) * p.rate_hz + 1e-6) + 1
    grid = t[0] + np.arange(n) / p.rate_hz
    keep = ~gap_mask(t, grid, p.max_gap_s)
    return np.arange(n)[keep] / p.rate_hz, resample_stream(t, v, grid, p.rate_hz, p.lowpass_order)[keep]


def clean_time(t: np.ndarray, *arrays: np.ndarray) -> tuple[np.ndarray, ...]:
    """Drop repeated time stamps (keep the first), so every stream is strictly increasing."""
    keep = np.ones(t.size, dtype=bool)
    keep[1:] = np.diff(t) > 0
    return (t[keep], *(a[keep] for a in arrays))
