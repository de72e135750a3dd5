"""evaluation.json: every model scored within its angle and across angle gaps, from the stored
predictions (the paper's Tables I-III in numbers; rendering lives in `pipeline.reporting`).

Per axis fx, fy, fz, over all samples of the evaluated set with its trials concatenated
("accuracy" = 100 - NRMSE, as in the abstract):
- within angle: each model on its own angle's external set (the paper's held-out "new
  dataset", Table I) and on its own angle's test split;
- angle-gap matrix: every angle's model on every angle's external set (the test split
  when an angle has no external rows), summarised per absolute gap as the mean NRMSE over
  all (train angle, data angle) pairs with that gap (Table II).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from needlecue_runtime.vocab import AXES, TRIAL_KEY, axes_of, sorted_angles
from pipeline.logs import Log
from pipeline.metrics.scores import gap_summary, gaps_present, mean_known, mean_over_axes, shared_scores
from pipeline.modelling.prediction_store import Predictions


@dataclass(frozen=True)
class EvalSet:
    """One angle's data: the set models are scored on, and its test split."""

    angle: str
    source: str  # "external", or "test" when the angle has no external rows
    frame: pd.DataFrame  # rows scored, with ids, t_s and forces
    test: pd.DataFrame

    @cached_property
    def axes(self) -> tuple[str, ...]:
        """The forces its reference recorded (the columns of `ref`)."""
        return axes_of(self.frame.columns)

    @cached_property
    def test_axes(self) -> tuple[str, ...]:
        return axes_of(self.test.columns)

    @cached_property
    def ref(self) -> np.ndarray:
        return self.frame[list(self.axes)].to_numpy(dtype=float)

    @cached_property
    def test_ref(self) -> np.ndarray:
        return self.test[list(self.test_axes)].to_numpy(dtype=float)


def load_eval_sets(data_dir: Path, angles: Iterable[str], log: Log) -> dict[str, EvalSet]:
    """Each angle's external and test split, read once; angles without data are skipped."""
    out: dict[str, EvalSet] = {}
    for angle in sorted_angles(angles):
        folder = data_dir / angle
        paths = {name: folder / f"{name}.parquet" for name in ("external", "test")}
        if not any(p.is_file() for p in paths.values()):
            log(f"warning: no data for angle {angle} in {folder}, skipped")
            continue
        frames = {
            name: pd.read_parquet(p) if p.is_file() else pd.DataFrame(columns=[*AXES])
            for name, p in paths.items()
        }
        external, test = frames["external"], frames["test"]
        if len(external):
            out[angle] = EvalSet(angle, "external", external, test)
        elif len(test):
            log(f"warning: angle {angle} has no external rows, scoring on its test split")
            out[angle] = EvalSet(angle, "test", test, test)
        else:
            log(f"warning: angle {angle} has neither external nor test rows, skipped")
    return out


@dataclass
class Scored:
    """Every prediction made, in the row order of the frame it was made on."""

    on_eval: dict[tuple[str, str, str], np.ndarray] = field(default_factory=dict)  # (model, train, data)
    on_test: dict[tuple[str, str], np.ndarray] = field(default_factory=dict)  # (model, angle)
    loaded: list[tuple[str, str]] = field(default_factory=list)  # (model, angle) that were found
    axes: dict[tuple[str, str], tuple[str, ...]] = field(default_factory=dict)  # (model, angle): its forces

    def axes_of(self, model: str, angle: str) -> tuple[str, ...]:
        """The forces model (model, angle) estimates: the columns of its predictions (all three
        unless `gather` found others)."""
        return self.axes.get((model, angle), AXES)


def gather(
    eval_sets: Mapping[str, EvalSet],
    predictions: Predictions,
    kinds: Sequence[str],
    angles: Sequence[str],
    log: Log,
) -> Scored:
    """The stored predictions of each (model, angle) on every angle's scored set and its own test split."""
    out = Scored()
    for model in kinds:
        for angle in angles:
            if not predictions.has(model, angle):
                log(f"warning: {model} at {angle}° skipped: no predictions (no trained model)")
                continue
            out.loaded.append((model, angle))
            out.axes[(model, angle)] = predictions.axes(model, angle)
            for data_angle, es in eval_sets.items():
                p = predictions.get(model, angle, data_angle, es.source)
                if p is None:
                    log(f"warning: {model}/{angle} has no predictions on {data_angle}° {es.source}")
                    continue
                out.on_eval[(model, angle, data_angle)] = p
            own = eval_sets.get(angle)
            if own is not None and len(own.test):
                p = predictions.get(model, angle, angle, "test")
                if p is not None:
                    out.on_test[(model, angle)] = p
    return out


def _n_trials(frame: pd.DataFrame) -> int:
    return int(frame[list(TRIAL_KEY)].drop_duplicates().shape[0]) if len(frame) else 0


def compute_metrics(
    eval_sets: Mapping[str, EvalSet], preds: Scored, gaps_deg: Sequence[float]
) -> dict[str, Any]:
    """The force scores of evaluation.json (`pipeline.metrics.document.Evaluation`; the evaluate stage
    adds the per-unit and cue sections, and `write_evaluation` rounds and writes it)."""
    within: dict[str, dict[str, Any]] = {}
    within_test: dict[str, dict[str, Any]] = {}
    matrix: dict[str, dict[str, dict[str, dict[str, float]]]] = {}
    for (model, train_angle, data_angle), p in preds.on_eval.items():
        es = eval_sets[data_angle]
        scores = shared_scores(p, preds.axes_of(model, train_angle), es.ref, es.axes)
        matrix.setdefault(model, {}).setdefault(train_angle, {})[data_angle] = {
            a: s["nrmse_pct"] for a, s in scores.items()
        }
        if train_angle == data_angle:
            within.setdefault(model, {})[train_angle] = scores
    for (model, angle), p in preds.on_test.items():
        es = eval_sets[angle]
        within_test.setdefault(model, {})[angle] = shared_scores(
            p, preds.axes_of(model, angle), es.test_ref, es.test_axes
        )

    angle_gap: dict[str, dict[str, Any]] = {}
    pairs: dict[str, dict[str, int]] = {}
    curve: dict[str, dict[str, Any]] = {}
    for model, mat in matrix.items():
        for gap in gaps_deg:
            summary, n = gap_summary(mat, float(gap))
            if n:
                angle_gap.setdefault(model, {})[f"{gap:g}"] = summary
                pairs.setdefault(model, {})[f"{gap:g}"] = n
        for gap in gaps_present(mat):
            summary, n = gap_summary(mat, gap)
            curve.setdefault(model, {})[f"{gap:g}"] = {
                **summary,
                "mean": mean_over_axes(summary),
                "n_pairs": n,
            }

    mean: dict[str, dict[str, Any]] = {}
    for model, per_angle in within.items():
        axes = [a for a in AXES if all(a in s for s in per_angle.values())]  # every angle's
        nrmse = {a: mean_known(s[a]["nrmse_pct"] for s in per_angle.values()) for a in axes}
        overall = mean_over_axes(nrmse)
        mean[model] = {
            "within_angle": nrmse,
            "within_angle_rmse": {a: mean_known(s[a]["rmse"] for s in per_angle.values()) for a in axes},
            "accuracy_pct": None if overall is None else 100.0 - overall,
            "n_angles": len(per_angle),
        }
        gap_acc = {g: mean_over_axes(s) for g, s in angle_gap.get(model, {}).items()}
        mean[model]["angle_gap_accuracy_pct"] = {
            g: None if v is None else 100.0 - v for g, v in gap_acc.items()
        }

    datasets = {
        angle: {
            "source": es.source,
            "n_rows": len(es.frame),
            "n_trials": _n_trials(es.frame),
            "n_test_rows": len(es.test),
            "batches": sorted(str(b) for b in es.frame["batch_id"].unique()),
        }
        for angle, es in eval_sets.items()
    }
    return {
        "within_angle": within,
        "within_angle_test": within_test,
        "angle_gap": angle_gap,
        "angle_gap_pairs": pairs,
        "angle_gap_matrix": matrix,
        "gap_curve": curve,
        "mean": mean,
        "datasets": datasets,
        "gaps_deg": [f"{g:g}" for g in gaps_deg],
        "models_evaluated": sorted(f"{m}/{a}" for m, a in preds.loaded),
    }
