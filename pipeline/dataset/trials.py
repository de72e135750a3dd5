"""The resampled trials read back for the split: one `Trial` per (batch, trial), its rows and what the
split rules need to know about it (channels, force axes, unit, purpose, front end, samples hash)."""

from __future__ import annotations

import json
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from needlecue_runtime.vocab import AXES, angle_name, axes_of
from pipeline.dataset.tables import columns_for
from pipeline.rig.repeats import SAMPLES_KEY

TrialKey = tuple[str, str]  # (batch_id, trial_id)


@dataclass(frozen=True)
class Trial:
    """One resampled trial: its rows and what the split needs to know about it."""

    batch_id: str
    trial_id: str
    angle: str  # folder name, vocab.angle_name(angle_deg)
    channels: tuple[str, ...]
    table: pa.Table
    axes: tuple[str, ...] = AXES  # the force axes its reference recorded
    unit_id: str = ""  # the estimator unit that recorded the batch
    purpose: str = "training"  # the batch's purpose: training | calibration
    front_end: dict[str, Any] | None = None  # the batch's batch.yaml sensor.front_end, as declared
    samples_sha256: str = ""  # its samples' hash from ingest (`pipeline.rig.repeats`)

    @property
    def key(self) -> TrialKey:
        return (self.batch_id, self.trial_id)


def load_trials(in_dir: Path) -> tuple[list[Trial], float | None]:
    """Every trial of every resampled batch, and the grid rate they share."""
    trials: list[Trial] = []
    rates: set[float] = set()
    for data_path in sorted(in_dir.glob("*.parquet")):
        meta_path = data_path.with_suffix(".json")
        if not meta_path.is_file():
            raise FileNotFoundError(f"{data_path}: no {meta_path.name} next to it (channels, rate_hz)")
        meta = json.loads(meta_path.read_text())
        channels = tuple(str(c) for c in meta["channels"])
        rates.add(float(meta["rate_hz"]))
        table = pq.read_table(data_path)
        axes = axes_of(table.column_names)
        if not axes:
            raise ValueError(f"{data_path}: no force column (one of {list(AXES)}) among {table.column_names}")
        missing = [c for c in columns_for(channels, axes) if c not in table.column_names]
        if missing:
            raise ValueError(f"{data_path}: columns {missing} missing (channels from {meta_path.name})")
        table = table.select(columns_for(channels, axes))
        if not isinstance(meta.get(SAMPLES_KEY), dict):
            raise ValueError(f"{meta_path}: no {SAMPLES_KEY} (written by an older resample: run dvc repro)")
        purpose = str(meta.get("purpose") or "training")
        batch = _split_by_trial(str(meta["batch_id"]), channels, table, purpose, meta.get("front_end"))
        missing_hash = sorted(t.trial_id for t in batch if t.trial_id not in meta[SAMPLES_KEY])
        if missing_hash:
            raise ValueError(f"{meta_path}: trials {missing_hash} have no {SAMPLES_KEY} entry")
        trials += [replace(t, samples_sha256=str(meta[SAMPLES_KEY][t.trial_id])) for t in batch]
    if len(rates) > 1:
        raise ValueError(f"resampled batches disagree on the grid rate: {sorted(rates)} Hz")
    return sorted(trials, key=lambda t: t.key), (rates.pop() if rates else None)


def _split_by_trial(
    batch_id: str, channels: tuple[str, ...], table: pa.Table, purpose: str, front_end: dict[str, Any] | None
) -> list[Trial]:
    ids = np.asarray(table.column("trial_id").to_pylist(), dtype=object)
    if ids.size == 0:
        return []
    order = np.argsort(ids.astype(str), kind="stable")
    sorted_ids = ids[order]
    cuts = np.flatnonzero(sorted_ids[1:] != sorted_ids[:-1]) + 1
    out = []
    for rows in np.split(order, cuts):
        part = table.take(pa.array(rows))
        angle = angle_name(part.column("angle_deg")[0].as_py())
        unit = str(part.column("unit_id")[0].as_py())
        axes = axes_of(part.column_names)
        out.append(Trial(batch_id, str(ids[rows[0]]), angle, channels, part, axes, unit, purpose, front_end))
    return out
