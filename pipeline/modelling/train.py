"""Training one angle's model from its processed folder into its model folder, and choosing a model
kind's inputs over all its angles' folders (the train and choose stages' work, callable from tests
and the benchmarks)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pandas as pd

from needlecue_runtime.frontend import Circuit, circuit_key
from needlecue_runtime.vocab import angle_name, file_sha256
from pipeline.dataset.splits import common_front_end, front_ends
from pipeline.logs import Log
from pipeline.modelling.checkpoint import save_model_dir
from pipeline.modelling.choice import Choice, pool
from pipeline.modelling.fit import choose, fit
from pipeline.modelling.kinds.base import KindParams


@dataclass(frozen=True)
class AngleData:
    """One angle's processed folder as its models read it."""

    train: pd.DataFrame
    val: pd.DataFrame  # may be empty
    sha256: str  # of the files read
    circuit: Circuit | None  # the circuit the training units declare
    other_designs: list[str]  # the angle's other units (held out, new) that declare another circuit


def load_angle(data_dir: Path) -> AngleData:
    """`data_dir/train.parquet`, `val.parquet` (may be absent) and the circuits of
    `front_ends.json`; FileNotFoundError or ValueError naming the folder when there is nothing to
    train on."""
    train_path, val_path = data_dir / "train.parquet", data_dir / "val.parquet"
    if not train_path.is_file():
        raise FileNotFoundError(f"{data_dir}: no train.parquet (run the split stage first)")
    train = pd.read_parquet(train_path)
    if train.empty:
        raise ValueError(f"{data_dir}: train.parquet has no rows, nothing to train on")
    val = pd.read_parquet(val_path) if val_path.is_file() else train.iloc[:0]
    units = [str(u) for frame in (train, val) if "unit_id" in frame for u in frame["unit_id"].unique()]
    circuits = front_ends(data_dir)
    circuit = common_front_end(circuits, units)
    mine = ("", circuit_key(circuit))  # the model serves the angle's other units too
    others = sorted(u for u, c in circuits.items() if u not in units and circuit_key(c) not in mine)
    sha = file_sha256([p for p in (train_path, val_path) if p.is_file()])
    return AngleData(train, val, sha, circuit, others)


def choose_folders(
    kind: str, params: KindParams, data_root: Path, angles: Sequence[float | str], log: Log
) -> Choice:
    """The inputs of `kind` (`inputs.kind: auto`) chosen once for all `angles`: each angle's choice
    (`data_root/<angle>`) pooled by the mean score (pipeline.modelling.choice.pool)."""
    by_angle = {}
    for angle in angles:
        name = angle_name(angle)
        data = load_angle(data_root / name)
        by_angle[name] = found = choose(kind, params, data.train, data.val, data.circuit, data.other_designs)
        log(f"{kind} at {name}°: {found.chosen}; mean NRMSE % {found.scores}")
    choice = pool(by_angle)
    log(f"{kind}: {choice.chosen} for all angles ({choice.folds}); mean NRMSE % {choice.scores}")
    return choice


def train_folder(
    kind: str, params: KindParams, data_dir: Path, out_dir: Path, log: Log, decided: Choice | None = None
) -> dict[str, Any]:
    """Fit `kind` on `data_dir/train.parquet`, early-stopping on `val.parquet` (may be empty or
    absent), reading through the circuit its units declare (`data_dir/front_ends.json`) and, with
    `inputs.kind: auto`, the inputs `decided` for all angles (`choose_folders`; None: chosen on this
    angle alone), and write the model folder; returns the metrics written."""
    data = load_angle(data_dir)
    label = f"{kind} on {data_dir}"
    log(f"{label}: {len(data.train)} train rows, {len(data.val)} val rows, {params.model_dump(mode='json')}")
    result = fit(
        kind,
        params,
        data.train,
        data.val,
        train_data_sha256=data.sha256,
        front_end=data.circuit,
        other_designs=data.other_designs,
        decided=decided,
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
