"""`train` stage: one model (ls, fnn or lstm) for one angle's processed data.

Input: `DATA_DIR/train.parquet` and `DATA_DIR/val.parquet` (the split stage's; val may be empty,
then the networks train all `max_epochs` without early stopping). Output in `OUT_DIR`:
`model.pt` (see `pipeline.models`), `train_metrics.json`, `history.csv` (epoch, train_loss, val_loss).
Only the model's own params section is read, so editing `fnn` never retrains `lstm`.

Usage: `python -m pipeline.train {ls|fnn|lstm} DATA_DIR OUT_DIR [--params params.yaml]`.
"""

from __future__ import annotations

import csv
import json
import math
import sys
from pathlib import Path
from typing import Any, cast

import pandas as pd
import typer

from pipeline.config import load_section
from pipeline.models import (
    CHECKPOINT_FILE,
    KINDS,
    PARAMS_MODELS,
    ModelParams,
    file_sha256,
    fit,
    save_checkpoint,
)

METRICS_FILE = "train_metrics.json"
HISTORY_FILE = "history.csv"


def _log(msg: str) -> None:
    print(f"train: {msg}", file=sys.stderr, flush=True)


def _json_safe(value: Any) -> Any:
    """NaN is not JSON: write null instead."""
    return None if isinstance(value, float) and math.isnan(value) else value


def run(model: str, data_dir: Path, out_dir: Path, params_path: Path) -> dict[str, Any]:
    """Train `model` on `data_dir`, write its three files to `out_dir`; returns the metrics."""
    if model not in KINDS:
        raise typer.BadParameter(f"unknown model {model!r}; expected one of {', '.join(KINDS)}")
    params = cast("ModelParams", load_section(PARAMS_MODELS[model], model, params_path))
    train_path, val_path = data_dir / "train.parquet", data_dir / "val.parquet"
    if not train_path.is_file():
        raise FileNotFoundError(f"{data_dir}: no train.parquet (run the split stage first)")
    train = pd.read_parquet(train_path)
    if train.empty:
        raise ValueError(f"{data_dir}: train.parquet has no rows, nothing to train {model} on")
    val = pd.read_parquet(val_path) if val_path.is_file() else train.iloc[:0]
    sha = file_sha256([p for p in (train_path, val_path) if p.is_file()])

    label = f"{model} on {data_dir}"
    _log(f"{label}: {len(train)} train rows, {len(val)} val rows, {params.model_dump(mode='json')}")
    result = fit(model, params, train, val, train_data_sha256=sha, log=lambda msg: _log(f"{label}: {msg}"))

    out_dir.mkdir(parents=True, exist_ok=True)
    save_checkpoint(result.checkpoint, out_dir / CHECKPOINT_FILE)
    # Wall time goes to the log only: in the DVC output it would change the model folder's hash
    # on every run although the weights are identical, and rerun `evaluate` for nothing.
    metrics = {k: _json_safe(v) for k, v in result.metrics.items() if k != "train_seconds"}
    (out_dir / METRICS_FILE).write_text(json.dumps(metrics, indent=2, sort_keys=True) + "\n")
    with (out_dir / HISTORY_FILE).open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=["epoch", "train_loss", "val_loss"], lineterminator="\n")
        writer.writeheader()
        writer.writerows(
            {k: ("" if _json_safe(v) is None else v) for k, v in row.items()} for row in result.history
        )
    m = result.metrics
    val_txt = "n/a (no val rows)" if m["best_val_loss"] is None else f"{m['best_val_loss']:.5f}"
    _log(
        f"{label}: done, {m['epochs_run']} epochs (best {m['best_epoch']}, val loss {val_txt}) "
        f"in {m['train_seconds']:.2f} s -> {out_dir}"
    )
    return metrics


def main(model: str, data_dir: Path, out_dir: Path, params: Path = Path("params.yaml")) -> None:
    """Train one model (ls, fnn or lstm) on one angle's processed data folder."""
    try:
        run(model, data_dir, out_dir, params)
    except (FileNotFoundError, ValueError) as e:  # bad input: one clear line, not a traceback
        _log(f"error: {e}")
        raise typer.Exit(1) from e


if __name__ == "__main__":
    typer.run(main)
