"""Labelling the phases of one trial (rest, insertion, dwell, retraction) from its reference force
on the common grid, and how long each phase lasted.
"""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pyarrow as pa
from scipy.ndimage import uniform_filter1d

from needlecue_runtime.vocab import PHASES


def label_phases(force_n: np.ndarray, rate_hz: float) -> np.ndarray:
    """Phase of every sample of one trial's reference force (n, axes: the one to three
    axes it records) on a uniform grid.

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


def phase_durations(table: pa.Table, rate_hz: float) -> pd.DataFrame:
    """Seconds of each phase per trial (rows: batch_id, trial_id; columns: PHASES)."""
    if table.num_rows == 0:
        return pd.DataFrame(columns=list(PHASES), dtype=float)
    df = table.select(["batch_id", "trial_id", "phase"]).to_pandas()
    counts = df.groupby(["batch_id", "trial_id", "phase"]).size().unstack(fill_value=0)
    return counts.reindex(columns=list(PHASES), fill_value=0) / rate_hz
