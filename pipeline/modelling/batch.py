"""Batch prediction: every model on every processed split of every angle, computed once and
written to the predictions store (`pipeline.modelling.predictions`) that evaluation, the cue packs,
the report and the registry read."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa

from pipeline.dataset.splits import SplitFiles
from pipeline.modelling.checkpoint import CHECKPOINT_FILE
from pipeline.modelling.features import InputTransform
from pipeline.modelling.predict import Predictor, load_predictor
from pipeline.modelling.predictions import UNCALIBRATED, prediction_table, write_predictions
from pipeline.vocab import AXES, SPLITS, angle_name, sorted_angles
from pipeline.workers import WORKERS, ordered_map

Log = Callable[[str], None]
UnitTransforms = Mapping[str, InputTransform]  # {unit_id: its calibration for one model}


def predict_frame(
    predictor: Predictor, frame: pd.DataFrame, what: str, transform: InputTransform | None = None
) -> np.ndarray:
    """Forces (n, 3) for a processed frame; the forces are dropped first, so that no model can read
    the answer, by mistake or otherwise."""
    inputs = frame.drop(columns=[a for a in AXES if a in frame])
    out = np.asarray(predictor.predict(inputs, transform), dtype=np.float64)
    if out.shape != (len(frame), len(AXES)):
        raise ValueError(f"{what}: predict returned shape {out.shape}, expected {(len(frame), len(AXES))}")
    return out


def predict_model(
    predictor: Predictor,
    frames: dict[tuple[str, str], pd.DataFrame],
    label: str,
    log: Log,
    units: UnitTransforms | None = None,
) -> list[pa.Table]:
    """One model's prediction blocks on every (angle, split) frame that has rows and its channels;
    external rows of the `units` with a calibration for this model go through it (and the same rows
    without it form the `UNCALIBRATED` block)."""
    parts: list[pa.Table] = []
    for (angle, split), frame in frames.items():
        if frame.empty:
            continue
        missing = [c for c in predictor.channels if c not in frame.columns]
        if missing:
            log(f"warning: {label} needs {missing}, absent at {angle}° {split}: not predicted there")
            continue
        what = f"{label} on {angle}° {split}"
        force = predict_frame(predictor, frame, what)
        parts.append(prediction_table(angle, split, force))
        if split == "external" and units and "unit_id" in frame.columns:
            calibrated = force.copy()
            for unit, transform in sorted(units.items()):
                mask = (frame["unit_id"] == unit).to_numpy()
                if mask.any():
                    rows = frame[mask]
                    calibrated[mask] = predict_frame(predictor, rows, f"{what}, unit {unit}", transform)
            if not np.array_equal(calibrated, force):
                parts[-1] = prediction_table(angle, split, calibrated)
                parts.append(prediction_table(angle, UNCALIBRATED, force))
    return parts


_FRAMES: dict[tuple[str, str], pd.DataFrame] = {}  # a worker's copy of the split frames


def _set_frames(frames: dict[tuple[str, str], pd.DataFrame]) -> None:
    _FRAMES.clear()
    _FRAMES.update(frames)


def _predict_one(job: tuple[str, str, Path, Path, UnitTransforms]) -> tuple[int, float, list[str]]:
    """One model's predictions on every split, written to its file: (rows, seconds, warnings)."""
    kind, angle, model_dir, target, units = job
    started = time.perf_counter()
    warnings: list[str] = []
    blocks = predict_model(load_predictor(model_dir), _FRAMES, f"{kind}/{angle}", warnings.append, units)
    rows = write_predictions(blocks, target)
    return rows, time.perf_counter() - started, warnings


def predict_all(
    data_dir: Path,
    models_dir: Path,
    out_dir: Path,
    kinds: Iterable[str],
    angles: Iterable[float | str],
    log: Log,
    workers: int = WORKERS,
    units: Mapping[tuple[str, str], UnitTransforms] | None = None,
) -> list[tuple[str, str]]:
    """Predict every (kind, angle) model that has a checkpoint on every split of every angle and
    write `out_dir/<kind>/<angle>.parquet`, on `workers` processes (each model's forward passes keep
    the one thread they were trained with, so the numbers do not depend on it); returns the
    (kind, angle) pairs predicted. `units` gives, per (kind, angle) model, the unit calibrations that
    apply to it."""
    files = SplitFiles(data_dir)
    frames = {
        (angle, split): files.frame(angle, split)
        for angle in files.angles()
        for split in SPLITS
        if files.path(angle, split).is_file()
    }
    jobs = []
    for kind in kinds:
        for angle in sorted_angles(angle_name(a) for a in angles):
            model_dir = Path(models_dir) / kind / angle
            target = Path(out_dir) / kind / f"{angle}.parquet"
            target.unlink(missing_ok=True)  # never leave a stale model's predictions behind
            if not (model_dir / CHECKPOINT_FILE).is_file():
                log(f"warning: no {model_dir / CHECKPOINT_FILE}, {kind} at {angle}° skipped")
                continue
            jobs.append((kind, angle, model_dir, target, dict((units or {}).get((kind, angle), {}))))
    for (kind, angle, *_), (rows, seconds, warnings) in zip(
        jobs, ordered_map(_predict_one, jobs, workers, _set_frames, (frames,)), strict=True
    ):
        for warning in warnings:
            log(warning)
        log(f"{kind}/{angle}: {rows} rows predicted ({seconds:.1f} s)")
    return [(kind, angle) for kind, angle, *_ in jobs]
