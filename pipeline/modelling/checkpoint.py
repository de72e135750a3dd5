"""Self-describing checkpoints: what a trained model is, and how to read and write it.

A checkpoint (`model.pt`) is a plain dict of tensors, strings, numbers, lists and dicts, so
`torch.load(path, weights_only=True)` reads it (no pickled objects), cf. nanoGPT's `GPTConfig`:
  format "needlecue-model/1"; kind (a `pipeline.modelling.kinds` name: "ls" | "fnn" | "lstm"); config
  `ModelConfig.to_dict()`; state_dict (the kind's: ls "weight" (3, channels) = C of eq. (1) and "bias"
  (3,), zeros without intercept; networks their module's state_dict); preprocessing {x_mean, x_std,
  y_mean, y_std} float64 (identity for ls); channels; inputs (the `<model>.inputs` params,
  `config.InputParams`: what the model computes from the volts; absent in older checkpoints = raw
  volts); targets ["fx", "fy", "fz"]; rate_hz; angle_deg; train_data_sha256; params (the params
  section it was trained with); torch_version.
"""

from __future__ import annotations

import csv
import hashlib
import json
import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import pandas as pd
from pydantic import Field, TypeAdapter, ValidationError

from needlecue_runtime.documents import Document

FORMAT = "needlecue-model/1"
CHECKPOINT_FILE = "model.pt"
METRICS_FILE = "train_metrics.json"
HISTORY_FILE = "history.csv"  # epoch, train_loss, val_loss


@dataclass(frozen=True)
class ModelConfig:
    """Everything needed to rebuild a model's modules from its state_dict (cf. nanoGPT's GPTConfig).

    `hidden` lists the widths of the hidden layers: () for `ls`, (20, 20) for the paper's FNN,
    (hidden,) * layers for the stacked LSTM. `window` is 1 for the memoryless models.
    """

    kind: str
    n_in: int
    n_out: int = 3
    hidden: tuple[int, ...] = ()
    activation: str = "identity"  # fnn: tanh | relu; lstm: tanh (inside its cell); ls: identity
    window: int = 1

    def to_dict(self) -> dict[str, Any]:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ModelConfig:
        return cls(**{**d, "hidden": tuple(d["hidden"])})


TENSORS = ("state_dict", "preprocessing")  # the checkpoint's groups of tensors; the rest is `CheckpointMeta`


class CheckpointMeta(Document):
    """What a checkpoint says of itself besides its tensors (the module docstring lists each field)."""

    format: Literal["needlecue-model/1"]
    kind: str = Field(min_length=1)  # whether it is known is `pipeline.modelling.kinds.kind_of`'s to say
    config: ModelConfig
    channels: list[str]
    inputs: dict[str, Any] | None = None  # `config.InputParams`; absent in older checkpoints: raw volts
    inputs_choice: dict[str, Any] | None = None  # `Choice.to_dict()`; None: pinned in params
    targets: list[str]
    rate_hz: float  # NaN: not estimated (no times)
    angle_deg: float
    train_data_sha256: str
    params: dict[str, Any]  # the kind's params section it was trained with
    torch_version: str


_META: TypeAdapter[CheckpointMeta] = TypeAdapter(CheckpointMeta)


def checkpoint_meta(checkpoint: Mapping[str, Any], where: str = "the checkpoint") -> CheckpointMeta:
    """The metadata of `checkpoint`, checked: ValueError naming `where` and the field (another format,
    a missing or renamed field, a missing group of tensors)."""
    if not isinstance(checkpoint, Mapping) or checkpoint.get("format") != FORMAT:
        fmt = checkpoint.get("format") if isinstance(checkpoint, Mapping) else type(checkpoint).__name__
        raise ValueError(f"{where}: not a {FORMAT} checkpoint (format {fmt!r})")
    missing = [g for g in TENSORS if not isinstance(checkpoint.get(g), Mapping)]
    if missing:
        raise ValueError(f"{where}: a {FORMAT} checkpoint without its {' and '.join(missing)}")
    try:
        return _META.validate_python({k: v for k, v in checkpoint.items() if k not in TENSORS})
    except ValidationError as e:
        raise ValueError(f"{where}: not a checkpoint this needlecue reads (train it again): {e}") from e


def check_checkpoint(checkpoint: dict[str, Any], what: str = "use") -> CheckpointMeta:
    """`checkpoint`'s metadata; ValueError unless it is a whole needlecue-model/1 checkpoint naming its
    kind (whether the kind is known is `pipeline.modelling.kinds.kind_of`'s to say)."""
    return checkpoint_meta(checkpoint, f"cannot {what} the checkpoint")


def save_checkpoint(checkpoint: dict[str, Any], path: Path) -> None:
    """`torch.save` of the plain dict (loadable with weights_only=True), once `checkpoint_meta` has
    checked it (ValueError naming the field, and nothing written)."""
    import torch

    checkpoint_meta(checkpoint, f"{path} (being written)")
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    torch.save(checkpoint, path)


def _json_safe(value: Any) -> Any:
    """NaN is not JSON: write null instead."""
    return None if isinstance(value, float) and math.isnan(value) else value


def save_model_dir(
    out_dir: Path, checkpoint: dict[str, Any], metrics: dict[str, Any], history: list[dict[str, float]]
) -> dict[str, Any]:
    """A model folder: `model.pt`, `train_metrics.json` and `history.csv`; returns the metrics written.

    Wall time is left out: in a DVC output it would change the folder's hash on every run although
    the weights are identical, and rerun everything downstream for nothing."""
    out_dir.mkdir(parents=True, exist_ok=True)
    save_checkpoint(checkpoint, out_dir / CHECKPOINT_FILE)
    written = {k: _json_safe(v) for k, v in metrics.items() if k != "train_seconds"}
    (out_dir / METRICS_FILE).write_text(json.dumps(written, indent=2, sort_keys=True) + "\n")
    with (out_dir / HISTORY_FILE).open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=["epoch", "train_loss", "val_loss"], lineterminator="\n")
        writer.writeheader()
        writer.writerows({k: ("" if _json_safe(v) is None else v) for k, v in row.items()} for row in history)
    return written


def read_train_metrics(model_dir: Path) -> dict[str, Any]:
    """A model folder's train_metrics.json ({} if it has none)."""
    path = Path(model_dir) / METRICS_FILE
    return json.loads(path.read_text()) if path.is_file() else {}


def load_checkpoint(model_dir_or_file: Path) -> dict[str, Any]:
    """The checkpoint dict of a model folder (its `model.pt`) or file, loaded with weights_only=True
    and checked (`checkpoint_meta`: ValueError naming the file and the field)."""
    import torch

    path = Path(model_dir_or_file)
    if path.is_dir():
        path = path / CHECKPOINT_FILE
    if not path.is_file():
        raise FileNotFoundError(f"no model checkpoint at {path}")
    checkpoint = torch.load(path, map_location="cpu", weights_only=True)
    checkpoint_meta(checkpoint, str(path))
    return checkpoint


def data_sha256(*frames: pd.DataFrame) -> str:
    """Content hash of in-memory frames (used when a model is not trained from files)."""
    h = hashlib.sha256()
    for f in frames:
        h.update(pd.util.hash_pandas_object(f, index=False).to_numpy().tobytes())
        h.update(b"\0")
    return h.hexdigest()


def checkpoint_sha256(checkpoint: dict[str, Any]) -> str:
    """Content hash of what the model computes: config, channels, inputs, targets and every tensor's
    name, dtype, shape and bytes. Unlike the bytes of `torch.save` (which embed a record id), it is equal
    for equal models. A checkpoint without `inputs` (raw volts) hashes as before they were recorded."""
    check_checkpoint(checkpoint, "hash")
    h = hashlib.sha256()
    # the stored values, not the typed ones: every registered checkpoint's hash stays
    keys = ("kind", "config", "channels", "targets") + (("inputs",) if "inputs" in checkpoint else ())
    head = {k: checkpoint[k] for k in keys}
    h.update(json.dumps(head, sort_keys=True).encode())
    for group in ("state_dict", "preprocessing"):
        tensors = checkpoint[group]
        for key in sorted(tensors):
            array = np.ascontiguousarray(tensors[key].detach().cpu().numpy())
            h.update(f"\0{group}.{key}:{array.dtype.str}:{array.shape}\0".encode())
            h.update(array.tobytes())
    return h.hexdigest()
