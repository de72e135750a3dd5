"""Training one angle's model from its processed folder into its model folder (the train stage's
work, callable from tests and the benchmark)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import pandas as pd

from pipeline.dataset.splits import common_front_end, front_ends
from pipeline.modelling.checkpoint import save_model_dir
from pipeline.modelling.fit import ModelParams, fit
from pipeline.rig.frontend import circuit_key
from pipeline.vocab import file_sha256

Log = Callable[[str], None]


def train_folder(kind: str, params: ModelParams, data_dir: Path, out_dir: Path, log: Log) -> dict[str, Any]:
    """Fit `kind` on `data_dir/train.parquet`, early-stopping on `val.parquet` (may be empty or
    absent), reading through the circuit its units declare (`data_dir/front_ends.json`), and write
    the model folder; returns the metrics written."""
    train_path, val_path = data_dir / "train.parquet", data_dir / "val.parquet"
    if not train_path.is_file():
        raise FileNotFoundError(f"{data_dir}: no train.parquet (run the split stage first)")
    train = pd.read_parquet(train_path)
    if train.empty:
        raise ValueError(f"{data_dir}: train.parquet has no rows, nothing to train {kind} on")
    val = pd.read_parquet(val_path) if val_path.is_file() else train.iloc[:0]
    sha = file_sha256([p for p in (train_path, val_path) if p.is_file()])
    label = f"{kind} on {data_dir}"
    log(f"{label}: {len(train)} train rows, {len(val)} val rows, {params.model_dump(mode='json')}")
    units = [str(u) for frame in (train, val) if "unit_id" in frame for u in frame["unit_id"].unique()]
    circuits = front_ends(data_dir)
    circuit = common_front_end(circuits, units)
    # the angle's other units (held out, new) that declare another circuit: the model serves them too
    mine = ("", circuit_key(circuit))
    others = sorted(u for u, c in circuits.items() if u not in units and circuit_key(c) not in mine)
    result = fit(
        kind,
        params,
        train,
        val,
        train_data_sha256=sha,
        front_end=circuit,
        other_designs=others,
        log=lambda m: log(f"{label}: {m}"),
    )
    written = save_model_dir(out_dir, result.checkpoint, result.metrics, result.history)
    m = result.metrics
    val_txt = "n/a (no val rows)" if m["best_val_loss"] is None else f"{m['best_val_loss']:.5f}"
    log(
        f"{label}: done, {m['epochs_run']} epochs (best {m['best_epoch']}, val loss {val_txt}) "
        f"in {m['train_seconds']:.2f} s -> {out_dir}"
    )
    return written
