"""Processed frames as trials for the cue code: time-ordered volts and forces, insertion span, and
the evidence the tracker would gather from a whole trial."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd

from needlecue_runtime.cues.evidence import MIN_VOLTS, Evidence, UnitMap
from needlecue_runtime.frontend import Circuit
from needlecue_runtime.vocab import AXES, TRIAL_KEY, axes_of, rate_hz
from pipeline.config import AUTO_EVIDENCE_LEVELS, CuesParams

AUTO_REACH = 0.9  # "auto" evidence levels end at the loading this share of training trials reach


@dataclass
class Trial:
    angle: float
    batch: str
    t: np.ndarray  # (n,)
    volts: np.ndarray  # (n, channels)
    force: np.ndarray  # (n, len(axes)) reference, N
    ins_start: int  # from the phase labels (-1 if none)
    ins_end: int
    rows: np.ndarray  # row positions in the source frame, time order
    unit: str | None = None  # the estimator unit that recorded it (None: the frame does not say)
    front_end: Circuit | None = None  # the circuit its unit declares (None: none declared)
    axes: tuple[str, ...] = AXES  # the force axes its reference recorded (the columns of `force`)
    unit_map: UnitMap | None = None  # the map its unit is read through (`cue_reading`), if any

    def force_on(self, axes: Sequence[str]) -> np.ndarray | None:
        """The reference force on `axes` (a pack's profile axes, in that order); None if its reference
        did not record one of them."""
        if not set(axes) <= set(self.axes):
            return None
        return self.force[:, [self.axes.index(a) for a in axes]]


def trials_of(
    frame: pd.DataFrame,
    channels: Sequence[str],
    angle: float,
    circuits: Mapping[str, Circuit | None] | None = None,
    maps: Mapping[str, UnitMap] | None = None,
) -> list[Trial]:
    """A processed frame's trials in (batch, trial) order, each with its unit's circuit from
    `circuits` ({unit_id: circuit}, processed `front_ends.json`) and the map it is read through from
    `maps` ({unit_id: map}; none: as it is)."""
    out = []
    if frame.empty:
        return out
    keys = [c for c in TRIAL_KEY if c in frame.columns]
    groups = frame.groupby(keys, sort=True).indices if keys else {("",): np.arange(len(frame))}
    t_all = frame["t_s"].to_numpy(np.float64)
    v_all = frame[list(channels)].to_numpy(np.float64)
    axes = axes_of(frame.columns)
    f_all = frame[list(axes)].to_numpy(np.float64) if axes else None
    ph_all = frame["phase"].to_numpy() if "phase" in frame.columns else None
    unit_all = frame["unit_id"].astype(str).to_numpy() if "unit_id" in frame.columns else None
    for key, idx in groups.items():
        idx = np.asarray(idx)
        idx = idx[np.argsort(t_all[idx], kind="stable")]
        if ph_all is not None:
            ins = np.flatnonzero(ph_all[idx] == "insertion")
            s, e = (int(ins[0]), int(ins[-1])) if len(ins) else (-1, -1)
        else:
            s = e = -1
        batch = str(key[0]) if isinstance(key, tuple) else str(key)
        force = f_all[idx] if f_all is not None else np.full((len(idx), len(AXES)), np.nan)
        unit = str(unit_all[idx[0]]) if unit_all is not None and len(idx) else None
        circuit = (circuits or {}).get(unit) if unit is not None else None
        recorded = axes or AXES
        unit_map = (maps or {}).get(unit) if unit is not None else None
        out.append(
            Trial(angle, batch, t_all[idx], v_all[idx], force, s, e, idx, unit, circuit, recorded, unit_map)
        )
    return out


def trials_rate_hz(trials: Sequence[Trial]) -> float:
    """The sample rate of trials: 1 / the median positive time step within each."""
    if not trials:
        return rate_hz([])
    t = np.concatenate([tr.t for tr in trials])
    groups = np.concatenate([np.full(len(tr.t), k) for k, tr in enumerate(trials)])
    return rate_hz(t, groups)


def run_evidence(trial: Trial, params: CuesParams, levels: Sequence[float] = ()) -> Evidence:
    """The evidence of a whole trial (causal code, fed frame by frame until the contact and every
    one of the loading `levels` are reached; none: the contact alone)."""
    return replay_evidence(trial, params, levels)[0]


def stage_frames(trial: Trial, starts: Sequence[int]) -> tuple[int, ...]:
    """Per evidence stage the trial reached (`starts`: the frame each became the latest, from
    `replay_evidence`), how many of its insertion frames (labelled 'insertion') the tracker spends
    with that stage's evidence as its latest: what a cue of that stage weighs for the trainee."""
    if trial.ins_start < 0:
        return (0,) * len(starts)
    ends = [*starts[1:], trial.ins_end + 1]
    first, last = trial.ins_start, trial.ins_end + 1
    return tuple(max(0, min(e, last) - max(s, first)) for s, e in zip(starts, ends, strict=True))


def replay_evidence(trial: Trial, params: CuesParams, levels: Sequence[float]) -> tuple[Evidence, list[int]]:
    """(the evidence of `run_evidence`, the frame at which each stage it reached became the latest:
    the rest reading when it is ready, then each loading level)."""
    ev = Evidence(
        trial.volts.shape[1],
        levels,
        params.contact_threshold,
        params.contact_samples,
        params.min_rest_s,
        trial.front_end,
        trial.unit_map,
    )
    starts: list[int] = []
    for i, (ti, vi) in enumerate(zip(trial.t.tolist(), trial.volts.tolist(), strict=True)):
        ev.push(ti, vi, None, i)
        if not starts and ev.rest_ready(ti):
            starts.append(i)
        while starts and len(starts) <= ev.stage:
            starts.append(i)
        if ev.contact_t is not None and ev.stage >= len(levels):
            break
    return ev, starts


def peak_loading(trial: Trial, params: CuesParams) -> float | None:
    """The largest loading a trial reaches after its contact, measured as the evidence measures its
    levels (the norm of the signal's log ratio to rest); None without a contact."""
    ev = run_evidence(trial, params)
    if ev.contact_t is None:
        return None
    return float(ev.loading(ev.signal(np.maximum(trial.volts[ev.contact_i :], MIN_VOLTS))).max())


def loading_levels(trials: Sequence[Trial], params: CuesParams) -> tuple[float, ...]:
    """The evidence levels: the params' own, or for "auto" AUTO_EVIDENCE_LEVELS evenly spaced up to
    the loading that AUTO_REACH of the (training) `trials` reach. Fixed levels suit one rig: the same
    push moves another design's signal more or less, and most insertions must pass every level."""
    if params.evidence_levels != "auto":
        return tuple(params.evidence_levels)
    peaks = [x for x in (peak_loading(tr, params) for tr in trials) if x is not None]
    if not peaks:
        return ()
    top = float(np.quantile(peaks, 1.0 - AUTO_REACH, method="lower"))  # a trial's own peak
    n = AUTO_EVIDENCE_LEVELS
    return tuple(top * k / n for k in range(1, n + 1))
