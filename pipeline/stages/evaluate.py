"""`evaluate` stage: every model scored within its angle and across angle gaps -> evaluation.json,
and its headline figures -> metrics.json.

Input: `DATA_DIR/<angle>/{external,test}.parquet` (the truth; `DATA_DIR/manifest.json` says which
units trained), the predict stage's `PRED_DIR` (the predictions), the units' calibrations in
`CAL_DIR` and the cues stage's `CUES_EVAL` (evaluation.json); nothing is predicted here. Output:
`EVALUATION_JSON`, every score (see `pipeline.metrics.evaluation`, per estimator unit
`pipeline.metrics.unit_transfer`, and the cues' headline `pipeline.metrics.cues`), which the report stage
renders and the register stage logs; `METRICS_JSON`, about thirty headline figures for DVC's tables
(`pipeline.metrics.headline`).

Usage:
`python -m pipeline.execution.run evaluate DATA_DIR PRED_DIR CAL_DIR CUES_EVAL EVALUATION_JSON METRICS_JSON
[--params params.yaml]`.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import typer

from needlecue_runtime.unit_calibration import calibrated_units, read_units
from needlecue_runtime.vocab import angle_name
from pipeline.config import EvaluateParams, TrainParams, load_section
from pipeline.cues.document import read_cue_evaluation
from pipeline.dataset.splits import unit_roles
from pipeline.logs import setup
from pipeline.metrics.cues import cue_headline
from pipeline.metrics.document import metrics_json, write_evaluation
from pipeline.metrics.evaluation import compute_metrics, gather, load_eval_sets
from pipeline.metrics.headline import headline
from pipeline.metrics.unit_transfer import by_unit, calibration_summary, champions_by_angle, unit_transfer
from pipeline.modelling.prediction_store import Predictions

_log = logging.getLogger("pipeline.stages").info  # not __name__: a stage runs as __main__


def main(
    data_dir: Path,
    pred_dir: Path,
    cal_dir: Path,
    cues_eval: Path,
    evaluation_json: Path,
    metrics_json_path: Path,
    params: Path = Path("params.yaml"),
) -> None:
    """Score the stored predictions as in the paper's sections V-VI, and per unit, into the full
    evaluation (what the report and the registry read) and its headline figures (metrics.json)."""
    setup("evaluate")
    start = time.perf_counter()
    train = load_section(TrainParams, "train", params)
    p = load_section(EvaluateParams, "evaluate", params)
    angles = [angle_name(a) for a in train.angles]
    try:
        eval_sets = load_eval_sets(data_dir, angles, _log)
        predictions = Predictions(pred_dir)
        scored = gather(eval_sets, predictions, list(train.kinds), angles, _log)
        roles = unit_roles(data_dir)
        units = read_units(cal_dir)
        cues = read_cue_evaluation(cues_eval) if cues_eval.is_file() else None
    except (FileNotFoundError, ValueError) as e:
        _log(f"error: {e}")
        raise typer.Exit(1) from e
    if not scored.loaded:
        _log(f"warning: no trained model found (no predictions under {pred_dir})")
    metrics = compute_metrics(eval_sets, scored, p.gaps_deg)
    calibrated = calibrated_units(units)
    kinds = list(train.kinds)
    metrics["by_unit"] = by_unit(eval_sets, predictions, kinds, roles, calibrated)
    metrics["by_unit_uncalibrated"] = by_unit(
        eval_sets, predictions, kinds, roles, calibrated, uncalibrated=True
    )
    champions = champions_by_angle(metrics["within_angle"], kinds)
    metrics["unit_transfer"] = unit_transfer(eval_sets, predictions, kinds, roles, calibrated, champions)
    metrics["calibration"] = calibration_summary(units)
    metrics["cues"] = cue_headline(cues)
    if cues is None:
        _log(
            f"warning: no cue evaluation at {cues_eval}: evaluation.json and metrics.json have no cue figures"
        )
    evaluation = write_evaluation(evaluation_json, metrics)
    metrics_json_path.parent.mkdir(parents=True, exist_ok=True)
    metrics_json_path.write_text(metrics_json(headline(evaluation)))
    elapsed = time.perf_counter() - start
    _log(f"{len(scored.loaded)} models on {len(eval_sets)} angles in {elapsed:.1f} s -> {metrics_json_path}")


if __name__ == "__main__":
    typer.run(main)
