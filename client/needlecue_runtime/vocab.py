"""The project's shared vocabulary: one home for each name every layer uses.

Column names of the processed data, the force axes, the model kinds, the rig-log id pattern
(shared with `params.yaml`'s unit ids), how an angle is named,
how a sample rate is estimated, how JSON outputs are rounded, and the deployable model's
contract. Numpy only, so the simulator's client can import it.
"""

from __future__ import annotations

import hashlib
import json
import math
import re
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

AXES = ("fx", "fy", "fz")  # the 3-D force, N, in the reference sensor's frame
TRIAL_KEY = ("batch_id", "trial_id")  # a trial is unique by both
# processed rows: unit_id is the estimator unit that recorded the batch (sensor.unit_id)
ID_COLUMNS = ("batch_id", "unit_id", "trial_id", "angle_deg", "tissue_point", "t_s", "phase")
PHASES = ("rest", "insertion", "dwell", "retraction")
NON_CHANNELS = frozenset({*ID_COLUMNS, *AXES})  # every other column of a processed frame is a channel
# the model kinds params.yaml may name (config.KindName), simplest first (ties go to the simpler): the
# names of `pipeline.modelling.kinds.TABLE` in its order (a test checks), which this light layer cannot load
KINDS = ("ls", "fnn", "lstm")
SPLITS = ("train", "val", "test", "external")
CALIBRATION = "calibration"  # batch purpose, and the processed folder of its trials (never a split)
# rig-log/1 batch, trial and unit ids (`docs/rig-log-format.md`, section 2; `pipeline.rig.format`)
ID_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,63}")

# The deployable model (pipeline.modelling.export writes it, needlecue_client reads it).
# /2: the graph reads the model's inputs (`inputs` in the metadata says how they are computed from
# volts: needlecue_runtime.features); /1 graphs read raw volts.
# /3: the description carries its graph's sha256 and the graph its description's (`description_sha256`)
# /4: the graph reads what the estimator sends (raw volts and their rest reading) and the unit's
# calibration as data, and computes the model's inputs itself (docs/deploy.md). Clients run /4 only.
DEPLOY_FORMAT = "needlecue-deploy/4"
DEPLOY_FORMATS = ("needlecue-deploy/1", "needlecue-deploy/2", "needlecue-deploy/3", DEPLOY_FORMAT)
# the graph's inputs, in order: the raw readings (batch, window, channels), counts or volts as the
# estimator sends them, the rest reading in effect at each of those samples (same shape), the volts of
# one reading unit (1,) (1 for volts, vref / (2^bits - 1) for counts), and the unit: matrix (channels,
# channels), offset (channels,), circuit (6,) (needlecue_runtime.features.unit_inputs)
INPUT_NAMES = ("reading", "rest_reading", "volts_per_count", "unit_matrix", "unit_offset", "unit_circuit")
OUTPUT_NAME = "force_n"


def format_problem(found: Any, expected: str, what: str, redo: str) -> str | None:
    """None if `found` is the format `expected`, else why a stored `what` cannot be read; one of ours
    from another needlecue version (the same name before the "/") says how to make a new one: `redo`."""
    if found == expected:
        return None
    ours = isinstance(found, str) and found.split("/")[0] == expected.split("/")[0]
    return f"not a {expected} {what} (format {found!r})" + (
        f": made by another needlecue version; {redo}" if ours else ""
    )


def angle_name(angle_deg: float | str) -> str:
    """Folder and key name of an angle: 30.0 -> "30", 22.5 -> "22.5", -0.0 -> "0"."""
    return f"{float(angle_deg) + 0.0:g}"


def sorted_angles(names: Iterable[str]) -> list[str]:
    """Angle names in numeric order, each once."""
    return sorted(set(names), key=lambda a: (float(a), a))


def axes_of(columns: Iterable[Any]) -> tuple[str, ...]:
    """The force axes among `columns` (a frame's, a table's, a dict's keys), in AXES order: what
    a reference recorded (docs/rig-log-format.md, `reference.axes`), what a model estimates."""
    names = {str(c) for c in columns}
    return tuple(a for a in AXES if a in names)


def axes_in_order(names: Any) -> bool:
    """Whether `names` (a list or tuple) are force axes a model may give (its `targets`): a non-empty
    subset of AXES, each once, in AXES order (("fx", "fy", "fz"), ("fz",), ...)."""
    return isinstance(names, list | tuple) and bool(names) and list(names) == [a for a in AXES if a in names]


def channels_of(frame: Any) -> list[str]:
    """The estimator channels of a processed frame (anything with `.columns`), in column order."""
    return [str(c) for c in frame.columns if c not in NON_CHANNELS]


def rate_hz(t: Sequence[float] | np.ndarray, groups: np.ndarray | None = None) -> float:
    """A stream's sample rate: 1 / the median positive time step, within each group (trial) if
    `groups` is given; nan with fewer than two distinct times. The median is robust to jitter and
    to dropped samples."""
    t = np.asarray(t, dtype=np.float64)
    if len(t) < 2:
        return math.nan
    if groups is None:
        dt = np.diff(np.sort(t))
    else:
        groups = np.asarray(groups)
        order = np.lexsort((t, groups))
        dt = np.diff(t[order])[groups[order][1:] == groups[order][:-1]]
    dt = dt[dt > 0]
    return float(1.0 / np.median(dt)) if len(dt) else math.nan


def jsonable(obj: Any, digits: int) -> Any:
    """Floats rounded to `digits` decimals (NaN/inf -> None, no "-0.0"), numpy scalars to Python,
    tuples to lists, keys to str: JSON that diffs well."""
    if isinstance(obj, Mapping):
        return {str(k): jsonable(v, digits) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [jsonable(v, digits) for v in obj]
    if isinstance(obj, bool | np.bool_):
        return bool(obj)
    if isinstance(obj, int | np.integer):
        return int(obj)
    if isinstance(obj, float | np.floating):
        x = float(obj)
        return round(x, digits) + 0.0 if math.isfinite(x) else None
    return obj


def dump_json(obj: Any, digits: int, indent: int = 2) -> str:
    """Deterministic JSON text: rounded (see `jsonable`), sorted keys, no NaN, newline-terminated."""
    return (
        json.dumps(jsonable(obj, digits), indent=indent, sort_keys=True, ensure_ascii=False, allow_nan=False)
        + "\n"
    )


def description_sha256(block: Mapping[str, Any]) -> str:
    """SHA-256 of a deployable model's description (its MLmodel `needlecue` block) without the
    block's `onnx_sha256`: the graph carries this hash and the block the graph's, so each vouches for
    the other (`needlecue_client.folder`). Canonical JSON: sorted keys, no spaces."""
    core = {k: v for k, v in block.items() if k != "onnx_sha256"}
    text = json.dumps(core, sort_keys=True, separators=(",", ":"), ensure_ascii=False, allow_nan=False)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def file_sha256(paths: Sequence[Path]) -> str:
    """SHA-256 of the concatenated bytes of files (the train and val parquet files, a model.onnx)."""
    h = hashlib.sha256()
    for p in paths:
        h.update(Path(p).read_bytes())
    return h.hexdigest()


_CONTROL = re.compile(r"[\x00-\x1f\x7f]")


def one_line(text: str) -> str:
    """`text` with its control characters (a newline in a folder's name) written as escapes: a
    reason or a log line stays one line."""
    return _CONTROL.sub(lambda m: repr(m.group())[1:-1], text)
