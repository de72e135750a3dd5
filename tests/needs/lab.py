"""A small lab for the needs tests: training units that record every angle on two batches each, each
unit's held-out trials, and a new unit with its held-out trials and a calibration batch (the cue
tests' synthetic estimator, `tests.cues.synthetic`)."""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

import pandas as pd

from pipeline.modelling.choice import Choice, save_choice
from pipeline.needs.curves import LabData
from tests.cues.synthetic import make_unit_split

# not 0°: there the synthetic fx is constant, and NRMSE divides by the reference's range
ANGLES = (15, 30, 45, 60)
TRAINING_UNITS = ("A", "B", "C")
NEW_UNIT = "D"
Frames = dict[str, dict[float, pd.DataFrame]]


def lab_frames(
    units: tuple[str, ...] = TRAINING_UNITS,
    per_batch: int = 2,
    angles: tuple[float, ...] = ANGLES,
    calibration_per_angle: int = 2,
) -> Frames:
    """{"train", "external", "calibration": {angle: rows}}: `per_batch` training insertions per unit,
    batch and angle; two held-out insertions per unit and angle (the new unit's too); the new unit's
    calibration batch."""
    train, external, calibration = {}, {}, {}
    for a in angles:
        batches = [
            make_unit_split(a, u, [f"{u}-b1", f"{u}-b2"], per_batch, seed=k + 1) for k, u in enumerate(units)
        ]
        train[float(a)] = pd.concat(batches, ignore_index=True)
        held = [
            make_unit_split(a, u, [f"{u}-held"], 2, seed=20 + k) for k, u in enumerate((*units, NEW_UNIT))
        ]
        external[float(a)] = pd.concat(held, ignore_index=True)
        calibration[float(a)] = make_unit_split(
            a, NEW_UNIT, [f"{NEW_UNIT}-cal"], calibration_per_angle, seed=50
        )
    return {"train": train, "external": external, "calibration": calibration}


def lab_data(frames: Frames) -> LabData:
    """The frames as the curves read them (no circuit declared: the cues read volts)."""
    return LabData(frames, {}, [NEW_UNIT] if frames.get("calibration") else [])


def write_lab(root: Path, frames: Frames) -> Path:
    """The frames as the split stage writes them, with a manifest naming each unit's role."""
    for split in ("train", "external"):
        for a, frame in frames[split].items():
            (root / f"{a:g}").mkdir(parents=True, exist_ok=True)
            frame.to_parquet(root / f"{a:g}" / f"{split}.parquet", index=False)
    (root / "calibration").mkdir(parents=True, exist_ok=True)
    for a, frame in frames.get("calibration", {}).items():
        frame.to_parquet(root / "calibration" / f"{a:g}.parquet", index=False)
    trained = {str(u) for f in frames["train"].values() for u in f["unit_id"].unique()}
    every = {str(u) for by in frames.values() for f in by.values() for u in f["unit_id"].unique()}
    units = {u: {"role": "training" if u in trained else "new"} for u in sorted(every)}
    (root / "manifest.json").write_text(json.dumps({"units": units}))
    return root


def write_choices(folder: Path, kind: str = "rest_volts", models: Sequence[str] = ("ls", "fnn")) -> Path:
    """The choose stage's files for `models` (LS and the FNN), each choosing `kind`."""
    for model in models:
        save_choice(folder / f"{model}.json", model, Choice(kind, {}, "leave-one-unit-out", "stand-in"))
    return folder
