"""A unit's calibration document (format "needlecue-unit/4", built by `pipeline.calibration.unit`) as
typed models: one writer (`write_unit`, the calibrate stage and `needlecue calibrate`) and one reader
(`read_unit`, or `parse_unit` for a document already in memory), both through `UnitCalibration`. A
renamed or missing field fails there, naming the file and the field. Numpy and pydantic only: the
simulator's client imports this module.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Literal

from pydantic import TypeAdapter, ValidationError

from needlecue_runtime.documents import Document, Number
from needlecue_runtime.features import InputTransform
from needlecue_runtime.frontend import Circuit, declared
from needlecue_runtime.vocab import angle_name, format_problem

FORMAT = "needlecue-unit/4"  # 4: a transform says its domain (conductance or the inputs)
DIGITS = 6  # decimals in the JSON: small, stable files
FILE = "calibration.json"  # its name in MLflow and in the client's cache
REDO = "calibrate the unit again"


class TrialUsed(Document):
    batch_id: str
    trial_id: str
    angle: str


class SetAside(Document):
    """A calibration trial not used, located by its batch, trial and estimator file, and why."""

    batch_id: str
    trial_id: str
    file: str
    angle: str
    reason: str


class Transform(Document):
    """One model kind's input transform, the models it applies to (their checkpoint hashes per
    angle), and what its fit did (`pipeline.calibration.fit`)."""

    matrix: list[list[float]]
    offset: list[float]
    domain: Literal["inputs", "conductance"]
    fitted_through: list[str]  # the angles it was fitted through
    models: dict[str, str]  # angle -> checkpoint sha256
    loss_before: Number
    loss_after: Number
    held_out_loss_before: Number = None  # absent: fitted through one angle, or not validated by angle
    held_out_loss_after: Number = None
    identity_kept: str | None = None  # why the identity was kept (absent: the fit is used)

    def input_transform(self, front_end: Circuit | None) -> InputTransform:
        """The transform (ValueError on a malformed matrix); a conductance-domain one reads through
        `front_end`, the circuit its unit declares."""
        return InputTransform.from_dict(
            {"matrix": self.matrix, "offset": self.offset, "domain": self.domain}, front_end
        )


class StageEvidence(Document):
    """A unit's evidence at one angle: per evidence stage, the trials reaching it and their mean
    features (`pipeline.cues.unit_evidence.evidence_of`)."""

    n: list[int]
    means: list[list[Number]]


class MappedEvidence(Document):
    """The evidence gathered through the unit's map on its conductance (`cue_map_kind`'s kind)."""

    kind: str
    matrix: list[list[float]]
    offset: list[float]
    evidence: dict[str, StageEvidence]


class UnitCues(Document):
    """What the unit's calibration insertions tell the cue packs' angle estimator."""

    levels: list[float]  # the loading levels the evidence was gathered at
    evidence: dict[str, StageEvidence]  # angle -> evidence
    mapped: MappedEvidence | None = None  # absent: no circuit declared, or no map kept


class UnitCalibration(Document):
    """One unit's calibration: which trials and angles it used, what was set aside and why, per model
    kind the input transform, the calibrate params, its declared circuit and its cue evidence."""

    format: Literal["needlecue-unit/4"]
    unit_id: str
    batches: list[str]
    trials: list[TrialUsed]
    angles_used: list[str]
    angles_missing: list[str]
    set_aside: list[SetAside]
    transforms: dict[str, Transform]
    params: dict[str, Any]  # the calibrate section it was made with (run params in the registry)
    front_end: dict[str, Any] | None  # the circuit its batches declare, as stored (None: none)
    cues: UnitCues | None = None  # absent: calibrated without the cue packs' params

    @property
    def circuit(self) -> Circuit | None:
        """The circuit the unit declares (None: none declared)."""
        return declared(self.front_end)

    def cue_section(self) -> dict[str, Any] | None:
        """The `cues` section as stored, the mapping the cue tracker reads
        (`needlecue_runtime.cues.units.cue_reading`); None without one."""
        return None if self.cues is None else self.cues.model_dump(mode="json", exclude_none=True)


_ADAPTER: TypeAdapter[UnitCalibration] = TypeAdapter(UnitCalibration)


def unit_text(doc: Mapping[str, Any]) -> str:
    """The bytes of a calibration document's file (and its sha256 in the registry): sorted keys,
    2-space indent, non-ASCII escaped, as every needlecue-unit/4 file was written."""
    return json.dumps(doc, indent=2, sort_keys=True) + "\n"


def parse_unit(doc: Any, where: str) -> UnitCalibration:
    """`doc` as a calibration document, checked: ValueError naming `where` and the fields (an older
    format is said as such), a malformed transform named by its kind."""
    found = doc.get("format") if isinstance(doc, dict) else type(doc).__name__
    problem = format_problem(found, FORMAT, "document", REDO)
    if problem:
        raise ValueError(f"{where}: {problem}")
    try:
        unit = _ADAPTER.validate_python(doc)
    except ValidationError as e:
        raise ValueError(f"{where}: not a calibration document this needlecue reads ({REDO}): {e}") from e
    circuit = unit.circuit
    for kind, t in unit.transforms.items():
        try:
            t.input_transform(circuit)
        except ValueError as e:
            raise ValueError(f"{where}: transform {kind!r}: {e}") from e
    return unit


def write_unit(doc: Mapping[str, Any], out_dir: Path) -> Path:
    """Write `doc` to `out_dir/<unit_id>.json` after checking it is a whole calibration document
    (ValueError naming the fields otherwise, and nothing written)."""
    unit = parse_unit(dict(doc), f"a calibration document for {out_dir} (being written)")
    path = Path(out_dir) / f"{unit.unit_id}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(unit_text(doc))
    return path


def read_unit(path: Path) -> UnitCalibration:
    """The calibration document at `path`, checked: ValueError naming the file if it is not one."""
    try:
        doc = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise ValueError(f"{path}: not a readable calibration document: {e}") from e
    return parse_unit(doc, str(path))


def transform_for(
    doc: UnitCalibration, kind: str, angle: float | str, checkpoint_sha: str
) -> InputTransform | None:
    """The unit's transform for a model, if it was calibrated with that very model (else None)."""
    t = doc.transforms.get(kind)
    if t is None or t.models.get(angle_name(angle)) != checkpoint_sha:
        return None
    return t.input_transform(doc.circuit)


def read_units(cal_dir: Path) -> dict[str, UnitCalibration]:
    """{unit_id: document} of every calibration document in `cal_dir` (none if it does not exist)."""
    cal_dir = Path(cal_dir)
    if not cal_dir.is_dir():
        return {}
    return {d.unit_id: d for d in (read_unit(f) for f in sorted(cal_dir.glob("*.json")))}


def calibrated_units(units: Mapping[str, UnitCalibration]) -> dict[str, bool]:
    """{unit_id: whether its document calibrates any model kind} (the identity kept counts: the
    calibration was made and applied)."""
    return {u: bool(d.transforms) for u, d in units.items()}
