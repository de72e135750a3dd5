"""Tracking: what a split file's MLflow dataset says about itself; the metrics and descriptions of a
model name its own axes (a model of fz alone: fz only)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from pipeline.registry.candidates import Trained
from pipeline.registry.tracking import axes_words, frame_schema, run_metrics
from pipeline.registry.versions import force_words

# MLflow hints about integer columns, and about its local dataset source (both beside the point here)
pytestmark = [
    pytest.mark.filterwarnings("ignore:Hint. Inferred schema contains integer"),
    pytest.mark.filterwarnings("ignore:The specified dataset source can be interpreted"),
]


def _frame(rows: int) -> pd.DataFrame:
    """Every kind of column a split file holds, and some it does not, with and without missing values."""
    rng = np.random.default_rng(0)
    values = rng.normal(size=rows)
    holes = np.where(np.arange(rows) % 5 == 3, np.nan, values)
    names = [f"t{i:03d}" for i in range(rows)]
    return pd.DataFrame(
        {
            "fsr1": values,
            "fx": holes,
            "f32": values.astype(np.float32),
            "count": np.arange(rows, dtype=np.int64),
            "small": np.arange(rows, dtype=np.uint8),
            "flag": np.arange(rows) % 2 == 0,
            "trial_id": pd.array(names, dtype="str"),
            "unit_id": pd.array([None if i % 4 == 1 else n for i, n in enumerate(names)], dtype="str"),
            "nullable": pd.array([None if i % 3 == 0 else n for i, n in enumerate(names)], dtype="string"),
            "nothing": pd.array([None] * rows, dtype="str"),
            "objects": pd.Series([n if i % 2 else None for i, n in enumerate(names)], dtype=object),
            "mixed": pd.Series([i if i % 2 else float(i) for i in range(rows)], dtype=object),
        }
    )


@pytest.mark.parametrize("rows", [1, 7, 300])
def test_the_schema_is_mlflows_own(rows: int) -> None:
    from mlflow.types.utils import _infer_schema

    # given: a frame with every kind of column, missing values in some
    frame = _frame(rows)
    # when / then: the schema computed a column at a time is the one MLflow infers value by value
    assert frame_schema(frame) == _infer_schema(frame)
    assert frame_schema(frame.iloc[:0]).input_names() == list(frame.columns)


# the columns of `_frame` whose schema is computed for the whole column at once
TYPED = {"fsr1", "fx", "f32", "count", "small", "flag", "trial_id", "unit_id", "nullable"}


class _Files:
    """The two calls `Datasets` makes of `pipeline.dataset.splits.SplitFiles`, on one frame."""

    def __init__(self, frame: pd.DataFrame) -> None:
        self._frame = frame

    def frame(self, angle: str, split: str) -> pd.DataFrame:
        return self._frame

    def path(self, angle: str, split: str) -> str:
        return f"data/processed/{angle}/{split}.parquet"


@pytest.mark.parametrize(
    "frame",
    [
        _frame(50)[sorted(TYPED)],
        # columns MLflow cannot describe: it logs no schema, and neither do we
        pd.DataFrame({"big": np.array([1, 2], dtype=np.uint64), "fx": [1.0, 2.0]}),
        pd.DataFrame({"z": np.array([1j, 2j]), "fx": [1.0, 2.0]}),
    ],
    ids=["split-file", "uint64", "complex"],
)
def test_a_logged_dataset_describes_itself_as_mlflow_would(
    frame: pd.DataFrame, monkeypatch: pytest.MonkeyPatch
) -> None:
    import mlflow.data
    from mlflow.types import utils

    from pipeline.registry.tracking import Datasets

    # given: a split file's dataset made the way tracking makes it, and MLflow's value-by-value test
    # of whether a column may be missing watched
    longest: list[int] = [0]
    required = utils._infer_required

    def watched(col: object) -> bool:
        longest[0] = max(longest[0], len(col) if isinstance(col, pd.Series) else 1)
        return required(col)

    monkeypatch.setattr(utils, "_infer_required", watched)
    ours = Datasets(_Files(frame)).get("15", "train")  # type: ignore[arg-type]
    # when: its record (name, digest, source, schema, profile) is written
    assert ours is not None
    record = ours.to_dict()
    walked = longest[0]
    # then: it is MLflow's own for the frame
    theirs = mlflow.data.from_pandas(frame, source="data/processed/15/train.parquet", name="15°-train")
    assert record == theirs.to_dict()
    # and, where every column is one the schema is computed for, no column was walked value by value
    if set(frame.columns) <= TYPED:
        assert walked <= 1


def _trained(targets: list[str]) -> Trained:
    """A model of `targets` with made-up scores on its axes only (what a reference of them gives)."""
    scores = {
        split: {a: {"rmse": 0.1 * (k + 1), "nrmse_pct": 2.0 * (k + 1)} for k, a in enumerate(targets)}
        for split in ("val", "test", "external")
    }
    checkpoint = {"targets": targets}
    return Trained("ls", "30", Path("models/ls/30"), "0" * 64, checkpoint, {"best_epoch": 1}, scores)


def test_a_model_of_fz_logs_metrics_of_fz_alone() -> None:
    # given: a model whose reference recorded fz alone, and one of all three axes
    one, three = _trained(["fz"]), _trained(["fx", "fy", "fz"])
    # when: their run metrics are made
    got_one, got_three = run_metrics(one, None), run_metrics(three, None)
    # then: fz and the mean over fz for the one, never a figure for fx or fy; all three for the other
    per_axis = {k.rsplit("_", 1)[1] for k in got_one if "_rmse_" in k or "_nrmse_pct_" in k}
    assert (
        per_axis == {"fz", "mean"} and got_one["external_nrmse_pct_mean"] == got_one["external_nrmse_pct_fz"]
    )
    assert got_one["external_accuracy_pct"] == 98.0
    assert {k.rsplit("_", 1)[1] for k in got_three if "_rmse_" in k} == {"fx", "fy", "fz", "mean"}
    assert got_three["external_nrmse_pct_mean"] == 4.0


def test_the_registered_descriptions_name_the_models_axes() -> None:
    # given / when / then: three axes read as before; one axis is named alone, never "mean of fx, fy, fz"
    assert force_words(["fx", "fy", "fz"]) == "3-D needle force (fx, fy, fz in N)"
    assert force_words(["fz"]) == "Needle force (fz in N)"
    assert axes_words(["fx", "fy", "fz"]) == "mean of fx, fy, fz"
    assert axes_words(["fz"]) == "fz" and axes_words(["fx", "fz"]) == "mean of fx, fz"
