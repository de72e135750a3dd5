"""evaluation.json as a typed document: one writer (`write_evaluation`, the evaluate stage), one
reader (`read_evaluation`: the report, the registry, `needlecue retrain`), both through these models.

Each model is frozen and forbids unknown fields, and every field is required: a section renamed on
one side fails where the file is written or read, not as an empty table in the report. Maps keyed by
data (model kind, angle, gap, unit) stay maps; a kind or angle with no results is simply absent.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

from pydantic import ConfigDict, TypeAdapter

from needlecue_runtime.documents import Document, DocumentFile, Number

EVALUATION_FILE = "evaluation.json"  # the full evaluation, in the reports folder (metrics.json: its headline)
DIGITS = 4  # precision of evaluation.json and metrics.json: 0.1 mN for RMSE, 0.0001 % for NRMSE

Axis = Literal["fx", "fy", "fz"]


class AxisScore(Document):
    """One axis of one (model, angle): RMSE (N) and NRMSE (% of the reference's range), eq. (3)-(4)."""

    rmse: Number
    nrmse_pct: Number


Scores = dict[Axis, AxisScore]  # the axes of one (model, angle): fx, fy, fz, or those recorded
AxisNrmse = dict[Axis, Number]  # NRMSE % per axis


class MeanNrmse(Document):
    """A model kind's scores averaged over its angles: what the paper reports too."""

    within_angle: AxisNrmse
    accuracy_pct: Number  # 100 - the mean of the axes


class MeanScores(MeanNrmse):
    within_angle_rmse: dict[Axis, Number]
    n_angles: int
    angle_gap_accuracy_pct: dict[str, Number]  # gap -> 100 - its mean NRMSE


class GapPoint(Document):
    """One gap of a model's gap curve: NRMSE % per axis, their mean, and how many pairs it averages."""

    fx: Number = None  # absent (None): an axis the reference did not record
    fy: Number = None
    fz: Number = None
    mean: Number
    n_pairs: int


class Dataset(Document):
    source: str  # "external" or "test"
    n_rows: int
    n_trials: int
    n_test_rows: int
    batches: list[str]


class UnitScores(Document):
    """One estimator unit's external rows: its role, whether it has a calibration, and each model
    kind's scores on them per angle (the kinds are the other keys)."""

    model_config = ConfigDict(frozen=True, extra="allow")
    __pydantic_extra__: dict[str, dict[str, Scores]]

    role: str
    calibrated: bool

    def kinds(self) -> dict[str, dict[str, Scores]]:
        """{kind: {angle: scores}} of every kind scored on this unit."""
        return dict(self.model_extra or {})

    def kind(self, kind: str) -> dict[str, Scores]:
        """{angle: scores} of `kind` on this unit ({} where it was not scored)."""
        return self.kinds().get(kind, {})


class TransferRow(Document):
    """Mean external NRMSE % over angles on the same unit, a new unit uncalibrated and calibrated,
    and new calibrated over same; `kinds` (the champion's row only): the kind at each angle."""

    same_unit: Number
    new_uncalibrated: Number
    new_calibrated: Number
    ratio: Number
    kinds: dict[str, str] | None = None


class KindLoss(Document):
    before: Number
    after: Number
    identity_kept: str | None  # why the identity was kept instead of the fit (None: the fit is used)


class CalibrationSummary(Document):
    """What a unit's calibration used and did (the calibrate stage's document, summarised)."""

    batches: list[str]
    n_trials: int
    angles_used: list[str]
    angles_missing: list[str]
    set_aside: list[str]
    loss: dict[str, KindLoss]


class CueFigures(Document):
    """What a trainee sees with a kind's combined cue in one unit group, in % (`pipeline.metrics.cues`)."""

    balanced_within_s: Number
    wrong_final: Number
    wrong_ever: Number
    wrong_frames: Number
    coverage_frames: Number
    trials: int


class ForceScores(Document):
    """The force scores the paper's comparisons read (`pipeline.metrics.paper`): ours, and the
    paper's own numbers in the same shape."""

    within_angle: dict[str, dict[str, Scores]]  # kind -> angle -> axes, on its own angle's scored set
    mean: dict[str, MeanNrmse]
    angle_gap: dict[str, dict[str, AxisNrmse]]  # kind -> gap -> axes
    gaps_deg: list[str]


class Evaluation(ForceScores):
    """Everything the evaluate stage scored (`pipeline.metrics.evaluation`, `.unit_transfer`, `.cues`)."""

    mean: dict[str, MeanScores]
    within_angle_test: dict[str, dict[str, Scores]]
    angle_gap_pairs: dict[str, dict[str, int]]
    angle_gap_matrix: dict[str, dict[str, dict[str, AxisNrmse]]]  # kind -> trained at -> scored at -> axes
    gap_curve: dict[str, dict[str, GapPoint]]
    datasets: dict[str, Dataset]
    models_evaluated: list[str]
    by_unit: dict[str, UnitScores]
    by_unit_uncalibrated: dict[str, UnitScores]
    unit_transfer: dict[str, TransferRow]  # kind | "champion" -> its row
    calibration: dict[str, CalibrationSummary]
    cues: dict[str, dict[str, CueFigures]]  # kind -> unit group -> figures


EVALUATION_DOC: DocumentFile[Evaluation] = DocumentFile(
    TypeAdapter(Evaluation), "an evaluation", "evaluate", DIGITS
)


def metrics_json(doc: dict[str, Any]) -> str:
    """Deterministic text of evaluation.json or metrics.json: rounded to DIGITS, sorted keys, no NaN."""
    return EVALUATION_DOC.text(doc)


def write_evaluation(path: Path, doc: dict[str, Any]) -> Evaluation:
    """Write evaluation.json, rounded to DIGITS, after checking `doc` is a whole `Evaluation`
    (ValueError naming the fields otherwise); returns it unrounded, as computed (the headline
    figures are computed from it, then rounded once)."""
    return EVALUATION_DOC.write(path, doc)


def read_evaluation(path: Path) -> Evaluation:
    """The evaluation.json at `path`; FileNotFoundError, or ValueError naming the file and fields."""
    return EVALUATION_DOC.read(path)
