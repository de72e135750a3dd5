"""The cue pack (`reports/cues/packs/<angle>.json`, shipped in each angle's registered model) as a
typed document, with the names the cue code shares: the cues, the verdicts, the methods.

One writer (`write_pack`, the cues stage) and one reader (`read_pack`; `as_pack` for a pack that came
inside a model's metadata). `build_cue_pack` (`pipeline.cues.packs`) makes the dict; these models check
it: a renamed or missing field fails where the pack is written or read, naming the file and the field.
The file's text is `pack_json`'s (compact, sorted keys, significant digits rounded where it was built),
not `DocumentFile`'s rounding. Numpy and pydantic only: the simulator's client imports this module.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import TypeAdapter

from needlecue_runtime.documents import Document, DocumentFile
from needlecue_runtime.frontend import Circuit, declared
from needlecue_runtime.vocab import format_problem

FORMAT = "needlecue-cues/5"  # 5: a unit's class means with their uncertainty (4: levels in the signal read)
# "wait": the rest reading is being collected; "none": no angle cue, the evidence does not decide
CUES = ("wait", "continue", "correct", "stop", "none")
VERDICTS = CUES[1:4]  # the cues a deviation maps to
NO_CUE = CUES.index("none")
# why there is no angle cue (CueState.no_cue), in the trainee's words
NO_CUE_REASONS = {
    "uncalibrated": "uncalibrated unit",
    "undecided": "not enough evidence yet",
    "outside": "outside what training covered",
}
METHODS = ("combined", "paper")
DEVIATION_GROUPS = ("0", "15", "30", ">=45")
REFERENCE = "reference"  # profile thresholds calibrated on the reference force (no model)
READINGS = ("training", "calibrated", "uncalibrated")  # how the estimator knows a unit (`reading_of`)


def cue_for_deviation(dev_deg: float, continue_below: float = 7.5, stop_from: float = 22.5) -> str:
    """continue / correct / stop for an absolute angle deviation in degrees."""
    d = abs(dev_deg)
    return "continue" if d < continue_below else ("correct" if d < stop_from else "stop")


def sig(x: float, digits: int = 6) -> float:
    """A float rounded to `digits` significant digits (small, stable JSON)."""
    return float(f"{float(x):.{digits}g}") + 0.0


def siglist(a: Any, digits: int = 6) -> Any:
    """`sig` of every number of an array, as nested lists."""
    arr = np.asarray(a, dtype=np.float64)
    if arr.ndim == 0:
        return sig(float(arr), digits)
    return [siglist(x, digits) for x in arr]


class StandardProfile(Document):
    """The reference force's mean and spread against time since the detected contact."""

    dt_s: float
    axes: list[str]
    mean_n: list[list[float]]  # (grid, axes)
    sd_n: list[list[float]]
    floor_n: float
    n_trials: int
    time_origin: str


class Cells(Document):
    """A unit's evidence at one angle: per evidence stage, its trials reaching it and their mean."""

    n: list[int]
    means: list[list[float]]


class EstimatorStage(Document):
    """One evidence stage of the angle estimator (`pipeline.cues.discriminant`)."""

    means: list[list[float]]  # the average unit's class means (classes, features)
    precision: list[list[float]]
    template_weight: float | None  # None: no unit's trials pull its means
    offset_spread: float | None  # None: too few training units to bound a new unit's offset
    temperature: float
    temperatures: dict[str, float]  # per reading of a unit left out ("uncalibrated", "calibrated-<k>")
    outside_limit: float | None
    n_train: int
    cv_accuracy: float | None


class Confidence(Document):
    """The P(deviation class) a cue needs for one reading, and what it gave in cross-validation."""

    min_confidence: float
    chosen_by: str
    cv_wrong_frames: float
    cv_coverage: float
    cv_frames: int


class AngleEstimator(Document):
    method: str
    features: str
    classes_deg: list[float]
    levels: list[float]
    stages: list[EstimatorStage]
    units: dict[str, dict[str, Cells]]  # {unit: {angle: its evidence}}
    cv: str
    confidence: dict[str, Confidence]  # per reading ("training", "calibrated-<k>", "uncalibrated")


class KindThresholds(Document):
    continue_below: float
    stop_from: float
    train_balanced_accuracy: float


class Thresholds(Document):
    profile: dict[str, KindThresholds]  # per model kind, or REFERENCE
    force_limit_n: float | None
    continue_below_deg: float
    stop_from_deg: float


class Training(Document):
    trials_per_angle: dict[str, int]
    batches: list[str]


class CuePack(Document):
    format: Literal["needlecue-cues/5"]
    preset_angle_deg: float
    angles: list[float]
    channels: list[str]
    rate_hz: float | None
    standard_profile: StandardProfile | None  # None: `unavailable` says why
    angle_estimator: AngleEstimator | None
    thresholds: Thresholds
    training: Training
    # the cues params it was built with, as dumped: the tracker checks them as `CuesParams`, so that
    # the pack's own check does not hang on every edit of the params' model
    params: dict[str, Any]
    front_end: dict[str, Any] | None  # the circuit its training units share (None: read in volts)
    unavailable: dict[str, str] | None = None  # what could not be built, and why (absent: all was)

    @property
    def estimator(self) -> AngleEstimator | None:
        """The angle estimator if it has a stage (else the tracker falls back to the paper's method)."""
        est = self.angle_estimator
        return est if est is not None and est.stages else None

    def why_missing(self, part: str, default: str) -> str:
        """Why `part` ("angle_estimator", "standard_profile", "thresholds.profile.<kind>") is missing."""
        return (self.unavailable or {}).get(part, default)


def pack_json(pack: Mapping[str, Any]) -> str:
    """A pack's file text: compact, sorted, strict JSON (what the client's model metadata carries)."""
    return json.dumps(pack, sort_keys=True, separators=(",", ":"), ensure_ascii=False, allow_nan=False) + "\n"


@dataclass(frozen=True)
class _PackFile(DocumentFile[CuePack]):
    """The pack's file: checked like every document, but its text is `pack_json`'s (the numbers
    were rounded where they were built, to significant digits, and the client's metadata embeds it)."""

    def text(self, doc: Any) -> str:
        return pack_json(doc)


PACK_DOC = _PackFile(TypeAdapter(CuePack), "a cue pack", "cues", digits=6)


def write_pack(path: Path, pack: Mapping[str, Any]) -> CuePack:
    """Write a pack (`build_cue_pack`'s dict) after checking it is a whole `CuePack`."""
    return PACK_DOC.write(path, pack)


def read_pack(path: Path) -> CuePack:
    """The pack at `path`; FileNotFoundError, or ValueError naming the file and the fields."""
    return PACK_DOC.read(path)


def pack_format_problem(pack: Any) -> str | None:
    """None if `pack` is a cue pack of this version's format, else why not."""
    if isinstance(pack, CuePack):
        return None
    found = pack.get("format") if isinstance(pack, Mapping) else type(pack).__name__
    return format_problem(found, FORMAT, "cue pack", "`dvc repro` builds and registers a new one")


def as_pack(pack: CuePack | Mapping[str, Any], where: str = "the cue pack") -> CuePack:
    """A pack as the typed document (a dict from a model's metadata or `build_cue_pack` is checked);
    ValueError if it is of another format or a field is missing or renamed."""
    if isinstance(pack, CuePack):
        return pack
    problem = pack_format_problem(pack)
    if problem:
        raise ValueError(problem)
    return PACK_DOC._parse(pack, where)


def pack_front_end(pack: CuePack) -> Circuit | None:
    """The circuit a pack's training units declared (its loading directions are in their FSRs'
    conductance), or None (in volts)."""
    return declared(pack.front_end)
