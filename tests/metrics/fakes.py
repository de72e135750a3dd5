"""Fake predictions for the evaluation tests: the truth plus an error set by the angle gap,
written where the predict stage writes, so evaluate and report run exactly as in the pipeline."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import pandas as pd

from needlecue_runtime.features import ModelInputs
from needlecue_runtime.vocab import AXES
from pipeline.metrics.document import Evaluation
from pipeline.metrics.evaluation import EvalSet, Scored, compute_metrics
from pipeline.modelling import prediction_store
from pipeline.modelling.split_predictions import predict_model
from tests.metrics.documents import evaluation

CHANNELS = ["fsr1", "fsr2", "fsr3"]
ANGLES = ["0", "15", "30", "45"]
AXIS_SCALE = np.array([1.0, 2.0, 3.0])  # per-axis error multiplier, so the axes differ

# error(model, train angle, data angle) -> constant offset (N) before AXIS_SCALE
ErrorFn = Callable[[str, float, float], float]


def gap_error(model: str, train: float, data: float) -> float:
    """0.1 N per 15° of gap, plus 0.001 N per 15° of train angle so that every pair differs."""
    return 0.1 * abs(train - data) / 15 + 0.001 * train / 15


def trial_frame(angle: float, batch: str, trial: str, n: int = 31) -> pd.DataFrame:
    """One trial whose forces equal its channels and span exactly [0, 1] N on every axis."""
    ramp = np.linspace(0.0, 1.0, n)
    cols = {
        "batch_id": [batch] * n,
        "trial_id": [trial] * n,
        "angle_deg": [float(angle)] * n,
        "tissue_point": ["p1"] * n,
        "t_s": np.arange(n) / 30.0,
        "phase": ["insertion"] * n,
    }
    for k, (ch, ax) in enumerate(zip(CHANNELS, AXES, strict=True)):
        values = np.roll(ramp, 3 * k)  # different shapes per axis, same [0, 1] range
        cols[ch] = values
        cols[ax] = values
    return pd.DataFrame(cols)


def angle_frame(angle: str, batch: str, n_trials: int = 2) -> pd.DataFrame:
    return pd.concat(
        [trial_frame(float(angle), batch, f"a{angle}-t{k:02d}") for k in range(1, n_trials + 1)],
        ignore_index=True,
    )


class FakePredictor:
    """Predicts the true force (readable from the channels) plus an error set by the angle gap."""

    def __init__(self, model: str, angle: str, error: ErrorFn = gap_error, channels: list[str] = CHANNELS):
        self.kind, self.angle_deg, self.channels = model, float(angle), tuple(channels)
        self.error = error
        self.inputs = ModelInputs()  # raw volts: no circuit to read through
        self.targets = AXES  # the forces it predicts

    def predict(self, frame: pd.DataFrame, transform: object = None, front_end: object = None) -> np.ndarray:
        assert transform is None and front_end is None, "no unit calibration or circuit in these tests"
        assert not set(AXES) & set(frame.columns), "forces must not reach the model"
        truth = frame[CHANNELS].to_numpy(dtype=float)
        data = frame["angle_deg"].to_numpy(dtype=float)
        offset = np.array([self.error(self.kind, self.angle_deg, d) for d in data])
        return truth + offset[:, None] * AXIS_SCALE


def write_processed(root: Path, angles: list[str] = ANGLES, no_external: tuple[str, ...] = ()) -> Path:
    """A tiny split-stage output: external and test files per angle."""
    for a in angles:
        d = root / a
        d.mkdir(parents=True)
        external = angle_frame(a, f"sim-heldout-{a}deg", 2)
        if a in no_external:
            external = external.iloc[:0]
        external.to_parquet(d / "external.parquet")
        angle_frame(a, "sim-tissue-1", 1).to_parquet(d / "test.parquet")
    return root


def write_predictions(
    pred_dir: Path,
    data_dir: Path,
    kinds: Sequence[str],
    angles: Sequence[str] = ANGLES,
    error: ErrorFn = gap_error,
    channels: Callable[[str, str], list[str]] = lambda _m, _a: CHANNELS,
    log: Callable[[str], None] = lambda _m: None,
) -> Path:
    """What the predict stage writes for fake models (kind, angle) of `models` x `angles`, on every
    split file under `data_dir`."""
    frames = {
        (d.name, f.stem): pd.read_parquet(f)
        for d in sorted(data_dir.iterdir())
        for f in sorted(d.glob("*.parquet"))
    }
    for m in kinds:
        for a in angles:
            blocks = predict_model(FakePredictor(m, a, error, channels(m, a)), frames, f"{m}/{a}", log)
            prediction_store.write_predictions(blocks, pred_dir / m / f"{a}.parquet")
    return pred_dir


def in_memory_metrics(error: ErrorFn, kinds: tuple[str, ...] = ("ls", "fnn", "lstm")) -> Evaluation:
    """The evaluation of all angles x models without touching disk (for the report tests): the force
    sections, the per-unit and cue sections empty."""
    angles = ["0", "15", "30", "45", "60", "75"]
    sets = {a: EvalSet(a, "external", angle_frame(a, "h"), angle_frame(a, "t", 1)) for a in angles}
    preds = Scored()
    for m in kinds:
        for t in angles:
            p = FakePredictor(m, t, error)
            preds.loaded.append((m, t))
            for d, es in sets.items():
                preds.on_eval[(m, t, d)] = p.predict(es.frame.drop(columns=list(AXES)))
            preds.on_test[(m, t)] = p.predict(sets[t].test.drop(columns=list(AXES)))
    return evaluation(**compute_metrics(sets, preds, (15, 30)))
