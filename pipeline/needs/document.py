"""needs.json as a typed document: one writer (`write_needs`, the needs stage) and one reader
(`read_needs`: the report); the advice reads the curves (`Curves`, everything but the advice) as the
file stores them (`stored_curves`). Every field is required: a section renamed on one side fails where
the file is written or read, naming the file and the field.

A force curve is named by the model kind it stands for: the kind itself where it is fitted as it is (a
kind whose inputs-choice stand-in is linear: the model itself), `<kind>_stand_in` where the networks'
stand-in is fitted in its place (`force_name`, `force_kind`).
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import Any, Literal

from pydantic import TypeAdapter, ValidationError

from needlecue_runtime.documents import Document, DocumentFile, Number
from pipeline.config import NeedsParams
from pipeline.modelling.kinds import TABLE, kind_label

FORMAT = "needlecue-needs/1"
FILE = "needs.json"
DIGITS = 6  # fractions to 0.0001 %, like evaluation.json
STAND_IN = "_stand_in"  # the suffix of a force curve fitted by a kind's stand-in


def force_name(kind: str, stand_in: bool) -> str:
    """The name of `kind`'s force curve: the kind, or `<kind>_stand_in` where its stand-in is fitted."""
    return f"{kind}{STAND_IN}" if stand_in else kind


def force_kind(name: str) -> tuple[str, bool]:
    """(the model kind, whether its stand-in is fitted) of a force curve's `name`."""
    return (name.removesuffix(STAND_IN), True) if name.endswith(STAND_IN) else (name, False)


def networks(fitted: Iterable[str]) -> str:
    """The kinds the networks' stand-in is not (every kind but those `fitted` as they are): "FNN or LSTM"."""
    kept = set(fitted)
    return " or ".join(kind_label(k) for k in TABLE if k not in kept)


class Seen(Document):
    """What the trainee sees, as fractions (`pipeline.needs.scoring.SEEN`)."""

    wrong_final: Number
    wrong_frames: Number
    coverage_frames: Number


class CueScores(Document):
    """The combined cue's figures on a scoring's test trials, as fractions."""

    balanced_within_s: Number
    recall_within_s: dict[str, Number]  # per class (stop, continue, correct)
    seen: Seen
    trials: int


class CueUnscored(Document):
    unavailable: str  # why the cues were not scored


CueFigures = CueScores | CueUnscored


class ScoresAt(CueScores):
    k: int  # calibration insertions per angle


class UnscoredAt(CueUnscored):
    k: int


class MeanUnscored(Document):
    k: int
    units: int  # 0: no unit left out was scored at k


class MeanScores(MeanUnscored):
    balanced_within_s: Number
    seen: Seen


class ForceFigures(Document):
    """One force curve at one step: mean NRMSE % over the angles, and per angle."""

    mean_nrmse_pct: Number
    by_angle: dict[str, Number]


class ForceModelAbout(Document):
    name: str  # `force_name`
    about: str


class Step(Document):
    """One step of the ladder: the trials subsampled, each force curve's figures, the cues."""

    per_angle: int
    trials: int
    by_unit: dict[str, int]
    batches: int
    force: dict[str, ForceFigures]
    cues: CueFigures | None  # None: no cue scoring at this step


class Training(Document):
    have_per_angle: dict[str, int]
    units: list[str]
    ladder: list[int]
    subsample: str
    force_models: list[ForceModelAbout]
    force_scored_on: str
    cues_scored_on: str
    steps: list[Step]


class NewUnit(Document):
    calibration_insertions: dict[str, int]  # angle -> its calibration insertions
    steps: list[ScoresAt | UnscoredAt]


class LeftOut(Document):
    test_trials: int
    steps: list[ScoresAt | UnscoredAt]


class LeaveOneUnitOut(Document):
    units: dict[str, LeftOut]
    mean: list[MeanScores | MeanUnscored]


class CalibrationCurves(Document):
    insertions_per_angle: list[int]
    force: str  # why force is not recomputed against calibration insertions
    new_units: dict[str, NewUnit]
    leave_one_unit_out: LeaveOneUnitOut | None  # None: fewer than two training units


class NotComputed(Document):
    what: str
    why: str


class Curves(Document):
    """The needs document without its advice: what the advice is computed from."""

    format: Literal["needlecue-needs/1"]
    params: NeedsParams
    cue_within_s: float
    training: Training
    calibration: CalibrationCurves
    not_computed: list[NotComputed]


class Needs(Curves):
    advice: list[str]  # what to record next, in words (`pipeline.needs.advice`)


NEEDS_DOC: DocumentFile[Needs] = DocumentFile(TypeAdapter(Needs), "a needs document", "needs", DIGITS)
_CURVES: DocumentFile[Curves] = DocumentFile(TypeAdapter(Curves), "a needs document", "needs", DIGITS)


def stored_curves(doc: dict[str, Any]) -> Curves:
    """The curves of `doc` (no advice yet) as needs.json stores them: rounded to DIGITS, then checked
    (ValueError naming the fields)."""
    try:
        return _CURVES.adapter.validate_json(_CURVES.text(doc))
    except ValidationError as e:
        raise ValueError(f"{FILE} (being written): not the curves this needlecue writes: {e}") from e


def write_needs(path: Path, doc: dict[str, Any]) -> Needs:
    """Write needs.json after checking `doc` is a whole `Needs` (ValueError naming the fields
    otherwise, and nothing written)."""
    return NEEDS_DOC.write(path, doc)


def read_needs(path: Path) -> Needs:
    """The needs.json at `path`; FileNotFoundError, or ValueError naming the file and the fields."""
    return NEEDS_DOC.read(path)
