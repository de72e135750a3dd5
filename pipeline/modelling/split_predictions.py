"""Prediction on the splits: every model on every processed split of every angle, computed once and
written to the predictions store (`pipeline.modelling.prediction_store`) that evaluation, the cue packs,
the report and the registry read."""

from __future__ import annotations

import time
from collections.abc import Iterable, Mapping
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa

from needlecue_runtime.features import InputTransform
from needlecue_runtime.frontend import Circuit
from needlecue_runtime.vocab import AXES, SPLITS, angle_name, sorted_angles
from pipeline.dataset.splits import SplitFiles
from pipeline.execution.workers import WORKERS, ordered_map, workers_for
from pipeline.logs import Log
from pipeline.modelling.checkpoint import CHECKPOINT_FILE
from pipeline.modelling.choice import Choice
from pipeline.modelling.prediction_store import (
    UNCALIBRATED,
    ModelReads,
    prediction_table,
    write_inputs,
    write_predictions,
)
from pipeline.modelling.predictor import Predictor, load_predictor

WORTH_A_WORKER = 500_000  # rows predicted, over all models: fewer take less than a worker's start
UnitTransforms = Mapping[str, InputTransform]  # {unit_id: its calibration for one model}


def predict_frame(
    predictor: Predictor,
    frame: pd.DataFrame,
    what: str,
    transform: InputTransform | None = None,
    front_end: Circuit | None = None,
) -> np.ndarray:
    """Forces (n, len(targets)) for a processed frame (read through `front_end`, the rows' unit's circuit, if
    given); the forces are dropped first, so that no model can read the answer, by mistake or
    otherwise."""
    inputs = frame.drop(columns=[a for a in AXES if a in frame])
    out = np.asarray(predictor.predict(inputs, transform, front_end), dtype=np.float64)
    expected = (len(frame), len(predictor.targets))
    if out.shape != expected:
        raise ValueError(f"{what}: predict returned shape {out.shape}, expected {expected}")
    return out


def predict_model(
    predictor: Predictor,
    frames: dict[tuple[str, str], pd.DataFrame],
    label: str,
    log: Log,
    units: UnitTransforms | None = None,
    circuits: Mapping[str, Circuit | None] | None = None,
) -> list[pa.Table]:
    """One model's prediction blocks on every (angle, split) frame that has rows and its channels;
    external rows of the `units` with a calibration for this model go through it (and the same rows
    without it form the `UNCALIBRATED` block). The rows of a unit that declares its own circuit
    (`circuits`, {unit_id: circuit}) are read through it."""
    parts: list[pa.Table] = []
    own = _own_circuits(predictor, circuits or {})
    for (angle, split), frame in frames.items():
        if frame.empty:
            continue
        missing = [c for c in predictor.channels if c not in frame.columns]
        if missing:
            log(f"warning: {label} needs {missing}, absent at {angle}° {split}: not predicted there")
            continue
        what = f"{label} on {angle}° {split}"
        # each row once: a unit with its own circuit through it, every other row as the training units
        force = np.zeros((len(frame), len(predictor.targets)))
        left = np.ones(len(frame), dtype=bool)
        for unit, circuit in own.items() if "unit_id" in frame.columns else ():
            mask = (frame["unit_id"] == unit).to_numpy()
            if mask.any():
                force[mask] = predict_frame(predictor, frame[mask], f"{what}, unit {unit}", None, circuit)
                left &= ~mask
        if left.all():
            force = predict_frame(predictor, frame, what)
        elif left.any():
            force[left] = predict_frame(predictor, frame[left], what)
        parts.append(prediction_table(angle, split, force, predictor.targets))
        if split == "external" and units and "unit_id" in frame.columns:
            calibrated = force.copy()
            for unit, transform in sorted(units.items()):
                mask = (frame["unit_id"] == unit).to_numpy()
                if mask.any():
                    rows = frame[mask]
                    calibrated[mask] = predict_frame(
                        predictor, rows, f"{what}, unit {unit}", transform, own.get(unit)
                    )
            if not np.array_equal(calibrated, force):
                parts[-1] = prediction_table(angle, split, calibrated, predictor.targets)
                parts.append(prediction_table(angle, UNCALIBRATED, force, predictor.targets))
    return parts


def _own_circuits(predictor: Predictor, circuits: Mapping[str, Circuit | None]) -> dict[str, Circuit]:
    """The units whose declared circuit differs from the one the model was trained through (only
    for inputs that read a circuit); a unit that declares none is read as the training units."""
    if not predictor.inputs.needs_circuit:
        return {}
    return {u: c for u, c in sorted(circuits.items()) if c is not None and c != predictor.inputs.front_end}


_FRAMES: dict[tuple[str, str], pd.DataFrame] = {}  # a worker's copy of the split frames


def _set_frames(frames: dict[tuple[str, str], pd.DataFrame]) -> None:
    _FRAMES.clear()
    _FRAMES.update(frames)


def _predict_one(
    job: tuple[str, str, Path, Path, UnitTransforms, Mapping[str, Circuit | None]],
) -> tuple[int, float, list[str], ModelReads]:
    """One model's predictions on every split, written to its file: (rows, seconds, warnings, what it
    reads)."""
    kind, angle, model_dir, target, units, circuits = job
    started = time.perf_counter()
    warnings: list[str] = []
    predictor = load_predictor(model_dir)
    blocks = predict_model(predictor, _FRAMES, f"{kind}/{angle}", warnings.append, units, circuits)
    rows = write_predictions(blocks, target, predictor.targets)
    choice = predictor.checkpoint.get("inputs_choice")
    reads = ModelReads(
        inputs=predictor.inputs,
        choice=None if choice is None else Choice(**choice),
    )
    return rows, time.perf_counter() - started, warnings, reads


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
    write `out_dir/<kind>/<angle>.parquet`, on up to `workers` processes (each model's forward passes keep
    the one thread they were trained with, so the numbers do not depend on it); returns the
    (kind, angle) pairs predicted. `units` gives, per (kind, angle) model, the unit calibrations that
    apply to it."""
    files = SplitFiles(data_dir)
    circuits = files.front_ends()
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
            jobs.append(
                (kind, angle, model_dir, target, dict((units or {}).get((kind, angle), {})), circuits)
            )
    inputs: dict[str, dict[str, ModelReads]] = {}
    workers = workers_for(len(jobs) * sum(len(f) for f in frames.values()), WORTH_A_WORKER, workers)
    for (kind, angle, *_), (rows, seconds, warnings, reads) in zip(
        jobs, ordered_map(_predict_one, jobs, workers, _set_frames, (frames,)), strict=True
    ):
        for warning in warnings:
            log(warning)
        inputs.setdefault(kind, {})[angle] = reads
        log(f"{kind}/{angle}: {rows} rows predicted ({seconds:.1f} s), inputs {reads.inputs.kind}")
    write_inputs(inputs, Path(out_dir))
    return [(kind, angle) for kind, angle, *_ in jobs]
