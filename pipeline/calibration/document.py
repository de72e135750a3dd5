"""Reading and writing a unit's calibration document (format "needlecue-unit/4", built by
`pipeline.calibration.unit`), and picking the transform that applies to one model. Numpy and json
only: the simulator's client imports this module."""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from pipeline.frontend import declared
from pipeline.modelling.features import InputTransform
from pipeline.vocab import angle_name, format_problem

FORMAT = "needlecue-unit/4"  # 4: a transform says its domain (conductance or the inputs)
DIGITS = 6  # decimals in the JSON: small, stable files
FILE = "calibration.json"  # its name in MLflow and in the client's cache


def write_unit(doc: Mapping[str, Any], out_dir: Path) -> Path:
    path = Path(out_dir) / f"{doc['unit_id']}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(doc, indent=2, sort_keys=True) + "\n")
    return path


def read_unit(path: Path) -> dict[str, Any]:
    """A calibration document, checked: ValueError naming the file if it is not one."""
    try:
        doc = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise ValueError(f"{path}: not a readable calibration document: {e}") from e
    found = doc.get("format") if isinstance(doc, dict) else type(doc).__name__
    problem = format_problem(found, FORMAT, "document", "calibrate the unit again")
    if problem:
        raise ValueError(f"{path}: {problem}")
    front_end = declared(doc.get("front_end"))
    for kind, t in (doc.get("transforms") or {}).items():
        try:
            InputTransform.from_dict(t, front_end)  # raises on a malformed matrix or domain
        except ValueError as e:
            raise ValueError(f"{path}: transform {kind!r}: {e}") from e
        if not isinstance(t.get("models"), dict):
            raise ValueError(f"{path}: transform {kind!r} does not say which models it applies to")
    return doc


def transform_for(
    doc: Mapping[str, Any], kind: str, angle: float | str, checkpoint_sha: str
) -> InputTransform | None:
    """The unit's transform for a model, if it was calibrated with that very model (else None)."""
    t = (doc.get("transforms") or {}).get(kind)
    if t is None or t.get("models", {}).get(angle_name(angle)) != checkpoint_sha:
        return None
    return InputTransform.from_dict(t, declared(doc.get("front_end")))


def read_units(cal_dir: Path) -> dict[str, dict[str, Any]]:
    """{unit_id: document} of every calibration document in `cal_dir` (none if it does not exist)."""
    cal_dir = Path(cal_dir)
    if not cal_dir.is_dir():
        return {}
    return {d["unit_id"]: d for d in (read_unit(f) for f in sorted(cal_dir.glob("*.json")))}


def calibrated_units(units: Mapping[str, Mapping[str, Any]]) -> dict[str, bool]:
    """{unit_id: whether its document calibrates any model kind} (the identity kept counts: the
    calibration was made and applied)."""
    return {u: bool(d.get("transforms")) for u, d in units.items()}
