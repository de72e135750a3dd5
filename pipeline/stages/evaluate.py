"""`evaluate` stage: every model scored within its angle and across angle gaps -> metrics.json.

Input: `DATA_DIR/<angle>/{external,test}.parquet` (the truth) and the predict stage's `PRED_DIR`
(the predictions); nothing is predicted here. Output: `METRICS_JSON` (see
`pipeline.metrics.evaluation`); the report stage renders it.

Usage: `python -m pipeline.run evaluate DATA_DIR PRED_DIR METRICS_JSON [--params params.yaml]`.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import typer

from pipeline.config import EvaluateParams, TrainParams, load_section
from pipeline.metrics.evaluation import compute_metrics, gather, load_eval_sets, metrics_json
from pipeline.modelling.predictions import Predictions
from pipeline.vocab import angle_name


def _log(msg: str) -> None:
    print(f"evaluate: {msg}", file=sys.stderr, flush=True)


def main(data_dir: Path, pred_dir: Path, metrics_json_path: Path, params: Path = Path("params.yaml")) -> None:
    """Score the stored predictions as in the paper's sections V-VI and write metrics.json."""
    start = time.perf_counter()
    train = load_section(TrainParams, "train", params)
    p = load_section(EvaluateParams, "evaluate", params)
    angles = [angle_name(a) for a in train.angles]
    try:
        eval_sets = load_eval_sets(data_dir, angles, _log)
        scored = gather(eval_sets, Predictions(pred_dir), list(train.models), angles, _log)
    except FileNotFoundError as e:
        _log(f"error: {e}")
        raise typer.Exit(1) from e
    if not scored.loaded:
        _log(f"warning: no trained model found (no predictions under {pred_dir})")
    metrics = compute_metrics(eval_sets, scored, p.gaps_deg)
    metrics_json_path.parent.mkdir(parents=True, exist_ok=True)
    metrics_json_path.write_text(metrics_json(metrics))
    elapsed = time.perf_counter() - start
    _log(f"{len(scored.loaded)} models on {len(eval_sets)} angles in {elapsed:.1f} s -> {metrics_json_path}")


if __name__ == "__main__":
    typer.run(main)
