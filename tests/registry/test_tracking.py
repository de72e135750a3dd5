"""Tracking: what a split file's MLflow dataset says about itself."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from pipeline.registry.tracking import frame_schema

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
