"""The store of predictions computed once: every model on every processed split of every angle.

The predict stage (`pipeline.modelling.split_predictions`) writes one file per model,
`PRED_DIR/<kind>/<angle>.parquet`, with one row per row of each split file it predicted, in that
file's row order:

    data_angle (str), split (str), row (int64: position in the split file), then the forces the model
    estimates, its checkpoint's `targets` (fx, fy, fz, or the axes its angle's reference records)
    (float64, N)

On the external split, rows of an estimator unit that has a calibration are predicted through the
unit's input transform; those models also get an `external-uncalibrated` block (`UNCALIBRATED`),
the same rows without it, so the report can show what calibration changed.

Evaluation, the cue packs and their scoring, the report and the registry all read these instead
of loading the models again. A model is predicted on a split only if the split has rows and holds
the model's channels; `Predictions.get` returns None otherwise.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from needlecue_runtime.features import ModelInputs, spec_of
from needlecue_runtime.vocab import AXES, angle_name, axes_of, sorted_angles
from pipeline.modelling.choice import Choice

UNCALIBRATED = "external-uncalibrated"  # the external rows predicted without any unit's calibration


def schema_for(axes: Iterable[str] = AXES) -> pa.Schema:
    """The schema of a model's predictions file: ids, then the forces it estimates."""
    ids = [("data_angle", pa.string()), ("split", pa.string()), ("row", pa.int64())]
    return pa.schema([*ids, *((axis, pa.float64()) for axis in axes)])


def prediction_table(angle: str, split: str, force: np.ndarray, axes: Iterable[str] = AXES) -> pa.Table:
    """The rows of one (angle, split) block: forces (n, len(axes)) in the split file's row order."""
    axes = tuple(axes)
    if force.ndim != 2 or force.shape[1] != len(axes):
        raise ValueError(f"forces of shape {force.shape} for the axes {list(axes)}")
    n = len(force)
    columns = {
        "data_angle": pa.array([angle] * n, pa.string()),
        "split": pa.array([split] * n, pa.string()),
        "row": pa.array(np.arange(n, dtype=np.int64)),
        **{axis: pa.array(force[:, k]) for k, axis in enumerate(axes)},
    }
    return pa.table(columns, schema=schema_for(axes))


INPUTS_FILE = "inputs.json"  # what each predicted model reads: {kind: {angle: {inputs, inputs_choice}}}


@dataclass(frozen=True)
class ModelReads:
    """What one trained model reads (its checkpoint's `inputs`) and how that was chosen (its
    `inputs_choice`; None: pinned in params)."""

    inputs: ModelInputs
    choice: Choice | None

    def to_dict(self) -> dict[str, Any]:
        choice = None if self.choice is None else self.choice.to_dict()
        return {"inputs": self.inputs.model_dump(mode="json"), "inputs_choice": choice}


def write_inputs(inputs: Mapping[str, Mapping[str, ModelReads]], pred_dir: Path) -> None:
    """INPUTS_FILE: each model's inputs and how they were chosen (from its checkpoint), for the report."""
    doc = {kind: {angle: r.to_dict() for angle, r in by_angle.items()} for kind, by_angle in inputs.items()}
    pred_dir.mkdir(parents=True, exist_ok=True)
    (pred_dir / INPUTS_FILE).write_text(json.dumps(doc, indent=2, sort_keys=True) + "\n")


def read_inputs(pred_dir: Path) -> dict[str, dict[str, ModelReads]]:
    """INPUTS_FILE's content ({} if the predict stage wrote none); ValueError naming the file and
    what is wrong when it is not one."""
    path = Path(pred_dir) / INPUTS_FILE
    if not path.is_file():
        return {}
    try:
        doc = json.loads(path.read_text())
        return {kind: {angle: _reads(r) for angle, r in by_angle.items()} for kind, by_angle in doc.items()}
    except (ValueError, KeyError, TypeError) as e:
        raise ValueError(f"{path}: not the predict stage's inputs record ({e!r}); rerun predict") from e


def _reads(record: Mapping[str, Any]) -> ModelReads:
    choice = record["inputs_choice"]
    return ModelReads(spec_of(record["inputs"]), None if choice is None else Choice(**choice))


def write_predictions(blocks: list[pa.Table], path: Path, axes: Iterable[str] = AXES) -> int:
    """One model's file of prediction blocks (forces on `axes`, the model's targets); returns its row
    count."""
    table = pa.concat_tables(blocks) if blocks else schema_for(axes).empty_table()
    path.parent.mkdir(parents=True, exist_ok=True)
    pq.write_table(table, path, compression="zstd")
    return table.num_rows


class Predictions:
    """The predict stage's output, read lazily: `get(kind, model_angle, data_angle, split)`."""

    def __init__(self, pred_dir: Path) -> None:
        self.pred_dir = Path(pred_dir)
        if not self.pred_dir.is_dir():
            raise FileNotFoundError(f"{self.pred_dir}: no such folder (run the predict stage first)")
        self._cache: dict[tuple[str, str], dict[tuple[str, str], np.ndarray]] = {}
        self._axes: dict[tuple[str, str], tuple[str, ...]] = {}

    def models(self) -> list[tuple[str, str]]:
        """(kind, angle) of every model with predictions, by kind folder then angle."""
        out = []
        for kind_dir in sorted(p for p in self.pred_dir.iterdir() if p.is_dir()):
            angles = sorted_angles(f.stem for f in kind_dir.glob("*.parquet"))
            out += [(kind_dir.name, a) for a in angles]
        return out

    def has(self, kind: str, angle: str) -> bool:
        return (self.pred_dir / kind / f"{angle}.parquet").is_file()

    def axes(self, kind: str, angle: str) -> tuple[str, ...]:
        """The forces model (kind, angle) estimates, the columns of what `get` returns (all three
        if it has no predictions)."""
        self._load(kind, angle)
        return self._axes[(kind, angle)]

    def _load(self, kind: str, angle: str) -> dict[tuple[str, str], np.ndarray]:
        if (kind, angle) not in self._cache:
            path = self.pred_dir / kind / f"{angle}.parquet"
            blocks: dict[tuple[str, str], np.ndarray] = {}
            axes = AXES
            if path.is_file():
                axes = axes_of(pq.read_schema(path).names)
                table = pq.read_table(path, schema=schema_for(axes)).to_pandas()
                for (data_angle, split), rows in table.groupby(["data_angle", "split"], sort=False):
                    force = np.empty((len(rows), len(axes)))
                    force[rows["row"].to_numpy()] = rows[list(axes)].to_numpy(np.float64)
                    blocks[(str(data_angle), str(split))] = force
            self._cache[(kind, angle)] = blocks
            self._axes[(kind, angle)] = axes
        return self._cache[(kind, angle)]

    def get(self, kind: str, model_angle: str, data_angle: str, split: str) -> np.ndarray | None:
        """Forces (n, len(axes)) of model (kind, model_angle) on `data_angle`'s `split`, in the split
        file's row order, on `axes(kind, model_angle)`; None if that model was not predicted there."""
        return self._load(kind, model_angle).get((data_angle, split))

    def on_split(
        self, kind: str, model_angle: str, split: str, angles: Iterable[float]
    ) -> dict[float, np.ndarray]:
        """{angle: forces} of one model on `split` of each of `angles` that it was predicted on."""
        found = {a: self.get(kind, model_angle, angle_name(a), split) for a in angles}
        return {a: f for a, f in found.items() if f is not None}
