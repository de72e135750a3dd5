"""Physical plausibility of one trial's streams, after their cells have parsed: values a sensor can
give, no isolated glitch, not a flat line, and a recording as long as one insertion.

Each check blames the first offending sample by file, line and column; the caller's ProblemLog sets
the trial aside. What is plausible comes from batch.yaml (the ADC's reference voltage, the reference
sensor's model, the robot's programme) and params.yaml `ingest` (the limits, each with a default).
docs/rig-log-format.md lists the checks and the reasons.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pandas as pd

from pipeline.config import IngestParams
from pipeline.rig.format import NEWTONS_PER_UNIT, BatchMeta
from pipeline.rig.problems import ProblemLog

MN_PER_N = 1000.0


def in_units(newtons: float, unit: str) -> float:
    """A force limit in N expressed in the reference file's `unit` (batch.yaml reference.units), so
    that the file's values are compared with the limit in newtons."""
    return newtons * MN_PER_N if unit == "mN" else newtons / NEWTONS_PER_UNIT[unit]


def reference_limit_n(meta: BatchMeta, p: IngestParams) -> float:
    """The largest |force| the batch's reference sensor reads, N: its model's range if params name
    it (`ingest.reference_max_n_by_model`), else `ingest.reference_max_n`."""
    return p.reference_max_n_by_model.get(meta.reference.model or "", p.reference_max_n)


def volts_limit(meta: BatchMeta, p: IngestParams) -> float:
    """The largest voltage an estimator channel in volts can read: the ADC's reference, else the
    default supply (`ingest.max_volts`)."""
    return meta.sensor.vref_v or p.max_volts


def protocol_s(meta: BatchMeta) -> float | None:
    """How long one insertion and its retraction take by the robot's programme, s (None if
    batch.yaml does not say)."""
    robot = meta.robot
    if robot is None or not robot.insertion_time_s:
        return None
    back = 1.0  # retraction at the insertion speed when batch.yaml gives no speeds
    if robot.insertion_speed_mm_s and robot.retraction_speed_mm_s:
        back = robot.insertion_speed_mm_s / robot.retraction_speed_mm_s
    return robot.insertion_time_s * (1.0 + back)


def _first(mask: np.ndarray) -> int:
    return int(np.flatnonzero(mask)[0])


def check_range(
    frame: pd.DataFrame, cols: Sequence[str], low: float, high: float, what: str, file: str, probs: ProblemLog
) -> None:
    """The first value of each column outside [low, high], blamed by line and column."""
    trial = str(frame["trial_id"].iat[0])
    for c in cols:
        v = frame[c].to_numpy(dtype=float)
        out = (v < low) | (v > high)
        if out.any():
            i = _first(out)
            reason = f"{c} = {v[i]:g} outside [{low:g}, {high:g}] {what}"
            probs.add(file, reason, trial_id=trial, line=int(frame["line"].iat[i]), column=c)


def check_glitches(
    frame: pd.DataFrame, cols: Sequence[str], jump: float, unit: str, knob: str, file: str, probs: ProblemLog
) -> None:
    """An isolated glitch: one sample that jumps more than `jump` from both neighbours, in opposite
    directions (a step, a puncture's drop, moves once and stays)."""
    trial = str(frame["trial_id"].iat[0])
    for c in cols:
        v = frame[c].to_numpy(dtype=float)
        if len(v) < 3:
            continue
        up, down = v[1:-1] - v[:-2], v[1:-1] - v[2:]
        spike = (np.abs(up) > jump) & (np.abs(down) > jump) & (np.sign(up) == np.sign(down))
        if spike.any():
            i = _first(spike) + 1
            reason = (
                f"glitch: {c} = {v[i]:g} {unit} between {v[i - 1]:g} and {v[i + 1]:g} "
                f"(a single sample jumping more than {knob} = {jump:g} {unit} and back)"
            )
            probs.add(file, reason, trial_id=trial, line=int(frame["line"].iat[i]), column=c)


def check_flat(frame: pd.DataFrame, cols: Sequence[str], what: str, file: str, probs: ProblemLog) -> None:
    """Every value column constant over the whole trial: a disconnected or frozen sensor."""
    if len(frame) < 2:
        return
    values = frame[list(cols)].to_numpy(dtype=float)
    if (values.max(axis=0) == values.min(axis=0)).all():
        reason = (
            f"{what} constant over all {len(frame)} samples "
            f"({', '.join(f'{c} = {values[0, k]:g}' for k, c in enumerate(cols))}): sensor disconnected?"
        )
        probs.add(file, reason, trial_id=str(frame["trial_id"].iat[0]), line=int(frame["line"].iat[0]))


def check_dead(frame: pd.DataFrame, cols: Sequence[str], what: str, file: str, probs: ProblemLog) -> None:
    """One column constant over the whole trial while another moves: a dead or disconnected channel
    (all constant is `check_flat`'s, and so is the one column of a one-axis reference)."""
    if len(frame) < 2:
        return
    values = frame[list(cols)].to_numpy(dtype=float)
    still = values.max(axis=0) == values.min(axis=0)
    if still.any() and not still.all():
        moving = [c for c, s in zip(cols, still, strict=True) if not s]
        for k in np.flatnonzero(still):
            reason = (
                f"{cols[k]} constant at {values[0, k]:g} over all {len(frame)} samples while "
                f"{', '.join(moving)} move: a dead or disconnected channel of the {what}"
            )
            line = int(frame["line"].iat[0])
            probs.add(file, reason, trial_id=str(frame["trial_id"].iat[0]), line=line, column=cols[k])


def check_clipped(
    frame: pd.DataFrame,
    cols: Sequence[str],
    time_col: str,
    per_second: float,
    min_run_s: float,
    what: str,
    file: str,
    probs: ProblemLog,
    rails: tuple[float, float] | None = None,
) -> None:
    """A flat top: the column held at the value farthest from its rest reading (its first sample) for
    at least `min_run_s` seconds on end, where the sensor or its logger saturated or clipped. A
    reading that rests on one value before the insertion is not flagged: only the far extreme is.
    With `rails` (an ADC's range), only a flat top on a rail: a 10-bit reading of a slow, quiet
    estimator holds its peak count for longer than that without being saturated."""
    if len(frame) < 3:
        return
    t = frame[time_col].to_numpy(dtype=float) / per_second
    trial = str(frame["trial_id"].iat[0])
    for c in cols:
        v = frame[c].to_numpy(dtype=float)
        lo, hi = float(v.min()), float(v.max())
        if lo == hi:
            continue  # constant: check_flat's or check_dead's
        far = hi if abs(hi - v[0]) >= abs(lo - v[0]) else lo
        if rails is not None and far not in rails:
            continue
        at = np.r_[False, v == far, False]
        starts, ends = np.flatnonzero(~at[:-1] & at[1:]), np.flatnonzero(at[:-1] & ~at[1:])
        spans = t[ends - 1] - t[starts]
        if spans.size and spans.max() >= min_run_s:
            i = int(starts[int(np.argmax(spans))])
            n = int((ends - starts)[int(np.argmax(spans))])
            reason = (
                f"{c} clipped: held at {far:g} {what}, its {'maximum' if far == hi else 'minimum'}, for "
                f"{spans.max():.3g} s ({n} samples) from this line; the sensor or its logger saturated "
                f"({'on its rail, ' if rails else ''}ingest.clip_run_s = {min_run_s:g} s or more)"
            )
            probs.add(file, reason, trial_id=trial, line=int(frame["line"].iat[i]), column=c)


def check_length(
    frame: pd.DataFrame,
    time_col: str,
    per_second: float,
    meta: BatchMeta,
    p: IngestParams,
    file: str,
    probs: ProblemLog,
) -> None:
    """A recording far longer than one insertion by the robot's programme (several insertions in one
    trial), or than `ingest.max_trial_s` when batch.yaml gives no programme."""
    t = frame[time_col].to_numpy(dtype=float)
    if len(t) < 2:
        return
    seconds = float(t[-1] - t[0]) / per_second
    one = protocol_s(meta)
    if one is not None:
        limit = one * p.max_trial_factor
        why = (
            f"one insertion and retraction take {one:g} s by the robot's programme in batch.yaml; "
            f"limit {limit:g} s (ingest.max_trial_factor = {p.max_trial_factor:g})"
        )
    else:
        limit, why = (
            p.max_trial_s,
            f"limit ingest.max_trial_s = {p.max_trial_s:g} s (no robot programme in batch.yaml)",
        )
    if seconds > limit:
        reason = (
            f"the recording lasts {seconds:g} s: {why}. Several insertions in one trial? "
            "Record each insertion as its own trial"
        )
        probs.add(
            file,
            reason,
            trial_id=str(frame["trial_id"].iat[0]),
            line=int(frame["line"].iat[-1]),
            column=time_col,
        )


# A forward step of a stream's clock is explained by lost samples up to this many of its median
# intervals, or up to MIN_JUMP_S, whichever is longer (docs/rig-log-format.md §8, "clock jump"): the
# simulator's longest step is 3 intervals (two samples lost in a row), a host-stamped serial stream's
# bursts and lost samples stay within a few; a step of 10 intervals at 30 Hz (0.33 s) is nine
# samples lost in a row. Longer honest losses are set aside too: the stamps alone cannot tell them from
# a jumped clock, and pairing readings with the force of seconds later is worse than losing the trial.
MAX_STEP_INTERVALS = 10.0
MIN_JUMP_S = 0.1  # a fast stream's (1 kHz) host or USB stall of tens of ms is lost samples, not a jump


def check_time_steps(
    frame: pd.DataFrame, time_col: str, per_second: float, stream: str, file: str, probs: ProblemLog
) -> None:
    """A forward step of the time that no sampling rate explains: longer than MAX_STEP_INTERVALS
    median intervals and than MIN_JUMP_S, a clock that jumped (every sample after it is stamped that
    much late). Blamed at the first sample after the step. (A step backwards or a repeated time is
    the expectations' "time does not increase".)"""
    t = frame[time_col].to_numpy(dtype=float)
    if len(t) < 3:
        return
    steps = np.diff(t)
    usable = np.isfinite(steps) & (steps > 0)
    if usable.sum() < 2:
        return
    median = float(np.median(steps[usable]))
    limit = max(MAX_STEP_INTERVALS * median, MIN_JUMP_S * per_second)
    jumps = usable & (steps > limit)
    if not jumps.any():
        return
    i = _first(jumps) + 1
    unit = "ms" if per_second == 1000.0 else "s"
    reason = (
        f"clock jump in the {stream}: {time_col} steps forward {steps[i - 1]:g} {unit} from the previous "
        f"sample, {steps[i - 1] / median:.0f} times its median interval of {median:.4g} {unit}; no sampling "
        f"rate explains it, and lost samples do not run past {MAX_STEP_INTERVALS:g} intervals and "
        f"{MIN_JUMP_S:g} s (every sample after it would pair with the wrong force)"
    )
    probs.add(
        file, reason, trial_id=str(frame["trial_id"].iat[0]), line=int(frame["line"].iat[i]), column=time_col
    )
