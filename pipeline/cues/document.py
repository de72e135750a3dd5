"""The cue evaluation (`reports/cues/evaluation.json`) as a typed document: one writer
(`write_cue_evaluation`, the cues stage), one reader (`read_cue_evaluation`: the evaluate and report
stages), both through these models.

A stage that could scored nothing writes a `SkippedCues`, saying why; otherwise a `ScoredCues`.
Every model is frozen and forbids unknown fields, and what a variant always has is required: a field
renamed on one side fails where the file is written or read, naming it, not as an empty table.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

from pydantic import TypeAdapter

from needlecue_runtime.documents import Document, DocumentFile, Number

FORMAT = "needlecue-cues-eval/1"
DIGITS = 6  # evaluation.json precision: fractions to 0.0001 %, like metrics.json's percentages


class Confusion(Document):
    """Counts, rows the true cue (continue, correct, stop), columns the cue shown (or none)."""

    rows_true: list[str]
    cols_cue: list[str]
    counts: list[list[int]]


class Seen(Document):
    """What a trainee sees: insertions ending on a wrong cue, showing one at any time, insertion
    frames showing one, and frames showing a cue at all (coverage); shares, 0 to 1."""

    wrong_final: Number
    wrong_ever: Number
    wrong_frames: Number
    coverage_frames: Number


class TimeToCue(Document):
    trials: int
    right_at_end: int
    never_right: int
    median_s: Number
    p90_s: Number
    seconds: list[float]


class GroupResult(Document):
    """One cue method of one model kind on a group of trials: what the per-unit-group scores keep."""

    within_s: float
    recall_within_s: dict[str, Number]  # per true cue: right, and staying right, within `within_s`
    balanced_within_s: Number  # their mean over the cues present
    accuracy_final: Number
    confusion_final: Confusion
    seen: Seen


class MethodResult(GroupResult):
    """One cue method of one model kind on every external trial."""

    confusion_frames: Confusion
    accuracy_frames: Number
    recall_final: dict[str, Number]
    time_to_cue: dict[str, TimeToCue]  # per deviation group
    force_alarm_trials: int | None  # the combined method's force alarms (None: another method)


Results = dict[str, dict[str, MethodResult]]  # kind (or the reference) -> method -> result


class AngleMatrix(Document):
    """The angle estimate at the insertion's end against the true angle (trials)."""

    rows_true_deg: list[float]
    cols_estimated_deg: list[float]
    counts: list[list[int]]
    exact: Number
    within_15: Number


class UnitGroup(Document):
    units: list[str]
    external_trials: dict[str, int] | None  # None: that group's evaluation was skipped
    results: dict[str, dict[str, GroupResult]]


class _Common(Document):
    format: Literal["needlecue-cues-eval/1"]
    kinds: list[str]  # the model kinds scored
    presets_deg: list[float]
    results: Results
    unavailable: dict[str, dict[str, str]] | None = None  # per preset angle: what its pack lacks, why
    by_unit_group: dict[str, UnitGroup] | None = None  # absent where no model kind could be scored


class SkippedCues(_Common):
    """Nothing could be scored: `skipped` says why."""

    skipped: str
    model_kinds_asked: list[str]


class ScoredCues(_Common):
    reference: str  # what results' reference entry is
    true_angles_deg: list[float]
    external_trials: dict[str, int]  # per true angle
    truth: str  # how the true cue follows from the angles
    angle_estimate_at_insertion_end: AngleMatrix | None  # None: the packs have no angle estimator


CueEvaluation = ScoredCues | SkippedCues


CUE_EVALUATION_DOC: DocumentFile[CueEvaluation] = DocumentFile(
    TypeAdapter(CueEvaluation), "a cue evaluation", "cues", DIGITS, indent=1
)


def write_cue_evaluation(path: Path, doc: dict[str, Any]) -> CueEvaluation:
    """Write the cue evaluation after checking it is a whole `ScoredCues` or `SkippedCues`
    (ValueError naming the fields otherwise)."""
    return CUE_EVALUATION_DOC.write(path, doc)


def read_cue_evaluation(path: Path) -> CueEvaluation:
    """The cue evaluation at `path`; FileNotFoundError, or ValueError naming the file and fields."""
    return CUE_EVALUATION_DOC.read(path)
