"""The rig-log/1 contract (`docs/rig-log-format.md`): file and column names, the id pattern (its one
home is `needlecue_runtime.vocab`, shared with params.yaml's unit ids), the `batch.yaml` models and `Problem`,
the one way any part of the pipeline says what is wrong.

Shared by the simulator (which writes such folders) and ingest (which reads them), so the two
can never disagree about the format.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass
from datetime import date
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_serializer, model_validator

from needlecue_runtime.frontend import FrontEnd
from needlecue_runtime.vocab import AXES, ID_PATTERN, one_line

FORMAT = "rig-log/1"
BATCH_FILE = "batch.yaml"
TRIALS_FILE = "trials.csv"
TRIAL_COLUMNS = ("trial_id", "angle_deg", "tissue_point")
REF_TIME = "t_s"
# the reference file's columns with every axis (batch.yaml `reference.axes` may declare fewer); the
# forces keep these names downstream (vocab.AXES)
REF_COLUMNS = (REF_TIME, *AXES)
REF_TORQUES = ("tx", "ty", "tz")
# batch.yaml `reference.units`: newtons per unit of the file (kg and g: kilogram- and gram-force, the
# standard gravity 9.80665 m/s²; lbf: pound-force). `signals.scaling.to_newtons` converts with it.
NEWTONS_PER_UNIT = {"N": 1.0, "mN": 1e-3, "g": 9.80665e-3, "kg": 9.80665, "lbf": 4.4482216152605}
RefUnit = Literal["N", "mN", "g", "kg", "lbf"]  # the keys of NEWTONS_PER_UNIT
Axis = Literal["fx", "fy", "fz"]  # vocab.AXES
FSR_TIME = "t_ms"


# Beyond rig-log/1's plain CSV, any CSV may be gzip-compressed (`<name>.gz`) and the reference
# stream may be an NI TDMS file (`<trial>.ref.tdms`, next to which NI software may write a
# `.tdms_index`): docs/rig-log-format.md, "Other forms of the same files".
GZIP = ".gz"
TDMS = ".tdms"
TDMS_INDEX = ".tdms_index"


def ref_columns(axes: Sequence[str] = AXES) -> tuple[str, ...]:
    """The reference file's required columns when batch.yaml's `reference.axes` is `axes`."""
    return (REF_TIME, *axes)


def undeclared_axes(axes: Sequence[str]) -> dict[str, str]:
    """{force axis a reference file must not have: why}, for batch.yaml's `reference.axes` = `axes`: a
    column batch.yaml does not declare is not quietly dropped (the lab says which axes it records)."""
    declared = ", ".join(axes)
    return {
        a: (
            f"column {a!r} is a force axis that batch.yaml's reference.axes ({declared}) does not declare: "
            f"add {a} to reference.axes, or leave the column out"
        )
        for a in AXES
        if a not in axes
    }


def fsr_file(trial_id: str) -> str:
    """Name of a trial's estimator stream file."""
    return f"{trial_id}.fsr.csv"


def ref_file(trial_id: str) -> str:
    """Name of a trial's reference stream file."""
    return f"{trial_id}.ref.csv"


def ref_tdms_file(trial_id: str) -> str:
    """Name of a trial's reference stream as an NI TDMS file."""
    return f"{trial_id}.ref{TDMS}"


def forms(name: str) -> tuple[str, ...]:
    """Every name a file of rig-log/1 (`trials.csv`, `<trial>.fsr.csv`, `<trial>.ref.csv`) may have."""
    out = (name, name + GZIP)
    if name.endswith(ref_file("")):
        out += (name.removesuffix(".csv") + TDMS,)
    return out


STREAM_SUFFIXES = (*forms(fsr_file("")), *forms(ref_file("")))  # a trial's file is <trial_id><suffix>


def find(folder: Path, name: str) -> list[Path]:
    """The files of `folder` that are `name` in one of its forms (`forms`): one, none or (ambiguous)
    several."""
    return [folder / n for n in forms(name) if (folder / n).exists()]


def is_valid_id(name: str) -> bool:
    """Whether `name` is a valid batch or trial id."""
    return ID_PATTERN.fullmatch(name) is not None


class _Meta(BaseModel):
    # Unknown keys are kept as metadata, never an error (rig-log/1).
    model_config = ConfigDict(extra="allow")


class SensorMeta(_Meta):
    """`sensor`: the estimator unit, its channels and their units."""

    # a unit's id names files (its calibration document) and registered models: an id, not a path
    unit_id: str = Field(pattern=rf"^{ID_PATTERN.pattern}$")
    channels: list[str] = Field(min_length=1)
    units: Literal["counts", "volts"]
    adc_bits: int | None = Field(None, ge=1, le=32)
    vref_v: float | None = Field(None, gt=0)
    # the circuit between each FSR and its channel (needlecue_runtime.frontend); absent: not declared
    front_end: FrontEnd | None = None

    @model_validator(mode="after")
    def _counts_need_adc(self) -> SensorMeta:
        if self.units == "counts" and (self.adc_bits is None or self.vref_v is None):
            raise ValueError("sensor.units is 'counts', so sensor.adc_bits and sensor.vref_v are required")
        bad = [c for c in self.channels if c in (FSR_TIME, "") or not isinstance(c, str)]
        if bad or len(set(self.channels)) != len(self.channels):
            raise ValueError(f"sensor.channels must be distinct column names other than {FSR_TIME!r}")
        return self


class ReferenceMeta(_Meta):
    """`reference`: the force/torque sensor, the force axes it records and their units."""

    model: str | None = None
    units: RefUnit
    frame: str | None = "tissue"
    # `shared`: both streams were stamped by one clock (t_s and t_ms / 1000 name the same instant),
    # so no offset is estimated; `separate` (the default): the reference runs on its own clock
    clock: Literal["separate", "shared"] = "separate"
    # the force axes the reference files hold (a one-axis load cell: [fz]), kept in the order of
    # vocab.AXES; the default, all three, is not written out (batch.json stays as it was)
    axes: list[Axis] = Field(default_factory=lambda: list(AXES))

    @field_validator("axes", mode="before")
    @classmethod
    def _one_axis_as_a_list(cls, value: Any) -> Any:
        return [value] if isinstance(value, str) else value  # `axes: fz` is `axes: [fz]`

    @field_validator("axes")
    @classmethod
    def _axes_once_each(cls, value: list[str]) -> list[str]:
        if not value:
            raise ValueError(f"name at least one force axis of {', '.join(AXES)}")
        if twice := sorted({a for a in value if value.count(a) > 1}):
            raise ValueError(f"lists {', '.join(twice)} more than once")
        return [a for a in AXES if a in value]

    @model_serializer(mode="wrap")
    def _axes_when_not_all(self, handler: Any) -> dict[str, Any]:
        out = handler(self)
        if tuple(self.axes) == AXES:
            out.pop("axes", None)
        return out


class RobotMeta(_Meta):
    """`robot`: the insertion programme (informative only)."""

    insertion_speed_mm_s: float | None = None
    insertion_time_s: float | None = None
    retraction_speed_mm_s: float | None = None


class BatchMeta(_Meta):
    """batch.yaml of one batch."""

    format: Literal["rig-log/1"]
    batch_id: str
    recorded: date | None = None
    tissue: dict[str, Any] | None = None
    sensor: SensorMeta
    reference: ReferenceMeta
    robot: RobotMeta | None = None
    # what the batch is for: `training` data, or a new unit's short `calibration` session, whose
    # trials never enter train/val/test/external (pipeline.dataset.split)
    purpose: Literal["training", "calibration"] = "training"

    def to_yaml_dict(self) -> dict[str, Any]:
        return self.model_dump(mode="json", exclude_none=True)


@dataclass(frozen=True)
class Problem:
    """One reason a batch, trial or file was set aside: what is wrong and exactly where."""

    batch_id: str
    file: str
    reason: str
    trial_id: str | None = None
    line: int | None = None
    column: str | None = None

    def __post_init__(self) -> None:
        # line numbers often come from numpy arrays; what is written to JSON must be plain int
        if self.line is not None:
            object.__setattr__(self, "line", int(self.line))

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    def __str__(self) -> str:
        where = self.file
        if self.line is not None:
            where += f":{self.line}"
        if self.column is not None:
            where += f" column {self.column!r}"
        return one_line(f"{where}: {self.reason}")


def batch_dirs(root: Path) -> list[Path]:
    """Candidate batch folders under a raw folder: every visible sub-directory, sorted.

    Files next to them (README, `*.dvc`, `.gitignore` written by `dvc add`) are not batches.
    """
    if not root.is_dir():
        return []
    return sorted(p for p in root.iterdir() if p.is_dir() and not p.name.startswith("."))
