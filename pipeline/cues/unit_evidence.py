"""Estimator units in the angle estimator. Units differ (part-to-part gain, cast-in preload, placement,
connector alignment: docs/physics.md §4) by more than the needle's weight and the loading direction
move the volts from one angle to the next, so the estimator reads every unit through its own class
means (`needlecue_runtime.cues.units.unit_readings`).

Per evidence stage, a trial's features (`Evidence.features`) are modelled as the angle's mean for the
average unit, plus the unit's offset, plus the unit's own departure at that angle, plus the trial's
scatter (one covariance shared by every unit and angle). The training units fit the angle means and
offsets by alternating means (`average_unit`). A unit's *evidence* is what the estimator keeps of it:
per angle and stage, how many of its trials reached the stage and their mean features. The training
units' evidence rides in the cue pack; a new unit's comes from its calibration insertions and rides
in its calibration document (`pipeline.calibration.unit`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd

from needlecue_runtime.cues.evidence import UnitMap
from needlecue_runtime.frontend import Circuit
from needlecue_runtime.vocab import angle_name, channels_of
from pipeline.config import CuesParams
from pipeline.cues.trials import Trial, loading_levels, replay_evidence, stage_frames, trials_of

ITERATIONS = 50  # alternating means converge in a few for the designs seen here; fixed for determinism
NO_UNIT = ""  # the unit of trials whose frame has no unit_id column


@dataclass(frozen=True)
class TrialFeatures:
    """One trial's evidence at the end of loading: every feature of the deepest stage it reached."""

    unit: str
    angle: float
    batch: str
    features: np.ndarray  # (channels * (stage + 1),)
    stage: int
    frames: tuple[int, ...] = ()  # per stage reached, its insertion frames (`stage_frames`)

    def at(self, j: int, n_ch: int) -> np.ndarray:
        """The features of stage j (the rest reading and the first j loading directions)."""
        return self.features[: n_ch * (j + 1)]


def _trials(
    frames_by_angle: Mapping[float, pd.DataFrame],
    channels: Sequence[str],
    circuits: Mapping[str, Circuit | None] | None,
    maps: Mapping[str, UnitMap] | None = None,
) -> list[Trial]:
    return [
        tr
        for angle in sorted(frames_by_angle, key=float)
        for tr in trials_of(frames_by_angle[angle], channels, float(angle), circuits, maps)
    ]


def training_levels(
    train_by_angle: Mapping[float, pd.DataFrame],
    params: CuesParams,
    circuits: Mapping[str, Circuit | None] | None = None,
) -> tuple[float, ...]:
    """The loading levels the angle estimator gathers its evidence at, from the training frames
    (what `trial_features` of them uses), for a new unit's evidence to match; () without frames."""
    frames = {a: f for a, f in train_by_angle.items() if len(f)}
    if not frames:
        return ()
    channels = channels_of(next(iter(frames.values())))
    return loading_levels(_trials(frames, channels, circuits), params)


def trial_features(
    frames_by_angle: Mapping[float, pd.DataFrame],
    channels: Sequence[str],
    params: CuesParams,
    circuits: Mapping[str, Circuit | None] | None = None,
    levels: Sequence[float] | None = None,
    maps: Mapping[str, UnitMap] | None = None,
) -> tuple[list[TrialFeatures], tuple[float, ...]]:
    """(the evidence of every trial with a rest reading, in angle then trial order, each read
    through its unit's circuit in `circuits`; the loading levels it was gathered at). `levels`: the
    angle estimator's (a new unit's evidence must be gathered at the training trials' levels); None:
    `loading_levels` of these trials."""
    trials = _trials(frames_by_angle, channels, circuits, maps)
    levels = loading_levels(trials, params) if levels is None else tuple(levels)
    out = []
    for tr in trials:
        ev, starts = replay_evidence(tr, params, levels)
        f = ev.features()
        if f is not None:
            unit = NO_UNIT if tr.unit is None else tr.unit
            frames = stage_frames(tr, starts)
            out.append(TrialFeatures(unit, tr.angle, tr.batch, np.asarray(f), ev.stage, frames))
    return out, levels


def evidence_of(trials: Sequence[TrialFeatures], n_ch: int) -> dict[str, dict[str, dict[str, Any]]]:
    """{unit: {angle: {"n": [trials reaching stage j], "means": [their mean stage-j features]}}} of
    the trials that name their unit."""
    cells: dict[str, dict[float, list[TrialFeatures]]] = {}
    for tf in trials:
        if tf.unit != NO_UNIT:
            cells.setdefault(tf.unit, {}).setdefault(tf.angle, []).append(tf)
    out: dict[str, dict[str, dict[str, Any]]] = {}
    for unit in sorted(cells):
        per: dict[str, dict[str, Any]] = {}
        for angle in sorted(cells[unit]):
            group = cells[unit][angle]
            top = max(tf.stage for tf in group)
            reached = [[tf.at(j, n_ch) for tf in group if tf.stage >= j] for j in range(top + 1)]
            per[angle_name(angle)] = {
                "n": [len(r) for r in reached],
                "means": [np.mean(r, axis=0).tolist() for r in reached],
            }
        out[unit] = per
    return out


def average_unit(
    cells: Mapping[tuple[str, int], np.ndarray], n_classes: int
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """(mu (classes, features): the average unit's class means, {unit: its offset}) from the cell
    means {(unit, class): mean features}, offsets centred on zero. Every class needs a cell."""
    units = sorted({u for u, _ in cells})
    width = len(next(iter(cells.values())))
    offset = {u: np.zeros(width) for u in units}
    mu = np.zeros((n_classes, width))
    for _ in range(ITERATIONS):
        mu = np.stack(
            [
                np.mean([m - offset[u] for (u, c2), m in cells.items() if c2 == c], axis=0)
                for c in range(n_classes)
            ]
        )
        offset = {u: np.mean([m - mu[c] for (u2, c), m in cells.items() if u2 == u], axis=0) for u in units}
        centre = np.mean(list(offset.values()), axis=0)
        offset = {u: d - centre for u, d in offset.items()}
    return mu, offset
