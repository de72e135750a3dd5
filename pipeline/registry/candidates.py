"""The trained models as candidates: each model folder with its scores on its own angle's
validation, test and external sets, computed from the stored predictions (nothing is predicted)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from needlecue_runtime.vocab import KINDS, axes_of
from pipeline.dataset.splits import SplitFiles
from pipeline.logs import Log
from pipeline.metrics.scores import mean_nrmse, shared_scores
from pipeline.modelling.checkpoint import checkpoint_sha256, load_checkpoint, read_train_metrics
from pipeline.modelling.prediction_store import Predictions

SPLITS = ("val", "test", "external")  # what each model is scored on


@dataclass(frozen=True)
class Trained:
    """One model folder and what the pipeline measured of it."""

    kind: str
    angle: str
    folder: Path
    model_sha256: str  # checkpoint_sha256: identifies what the model computes, not the file's bytes
    checkpoint: dict[str, Any]
    train_metrics: dict[str, Any]
    scores: dict[str, dict[str, dict[str, float]]]  # split -> axis -> {"rmse", "nrmse_pct"}

    @property
    def judged_on(self) -> str | None:
        """The split the champion rule scores this model on: the external set, or the test split
        for an angle without external rows (as evaluate does); None when neither has rows."""
        for split in ("external", "test"):
            scores = self.scores[split]
            if scores and all(np.isfinite(s["nrmse_pct"]) for s in scores.values()):
                return split
        return None

    def mean_nrmse(self, split: str | None = None) -> float:
        split = split or self.judged_on
        return float("nan") if split is None else mean_nrmse(self.scores[split])


def kind_rank(kind: str) -> int:
    """ls, fnn, lstm (simplest first), then any other kind."""
    return KINDS.index(kind) if kind in KINDS else len(KINDS)


def _scores(
    truth: pd.DataFrame, predicted: np.ndarray | None, targets: tuple[str, ...]
) -> dict[str, dict[str, float]]:
    """The scores on the axes both the model (its `targets`) and the truth have; NaN where unscored."""
    if truth.empty or predicted is None:
        return {a: {"rmse": float("nan"), "nrmse_pct": float("nan")} for a in targets}
    recorded = axes_of(truth.columns)
    return shared_scores(predicted, targets, truth[list(recorded)].to_numpy(np.float64), recorded)


def collect(
    models_dir: Path, files: SplitFiles, predictions: Predictions, candidates: tuple[str, ...], log: Log
) -> list[Trained]:
    """Every model with predictions, `models_dir/<kind>/<angle>`, scored on its angle's splits."""
    out: list[Trained] = []
    for kind, angle in predictions.models():
        folder = models_dir / kind / angle
        checkpoint = load_checkpoint(folder)
        targets = predictions.axes(kind, angle)
        scores = {
            split: _scores(files.frame(angle, split), predictions.get(kind, angle, angle, split), targets)
            for split in SPLITS
        }
        out.append(
            Trained(
                kind,
                angle,
                folder,
                checkpoint_sha256(checkpoint),
                checkpoint,
                read_train_metrics(folder),
                scores,
            )
        )
    if not out:
        raise FileNotFoundError(
            f"no trained model folders with predictions under {predictions.pred_dir} "
            "(run the train and predict stages)"
        )
    unknown = sorted({t.kind for t in out} - set(candidates))
    if unknown:
        log(f"not deployable by register.candidates, tracked only: {', '.join(unknown)}")
    return out
