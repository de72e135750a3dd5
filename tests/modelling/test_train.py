"""Training one angle's model folder: what reaches the model, empty splits, errors."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import pytest
import torch

from pipeline.config import load_section
from pipeline.modelling.checkpoint import load_checkpoint
from pipeline.modelling.kinds import kind_of
from pipeline.modelling.train import train_folder
from tests.modelling.folders import PARAMS, write_split
from tests.modelling.frames import make_frame


@pytest.fixture
def params_file(tmp_path: Path) -> Path:
    path = tmp_path / "params.yaml"
    path.write_text(PARAMS)
    return path


def run(kind: str, data: Path, out: Path, params_file: Path) -> dict[str, Any]:
    params = load_section(kind_of(kind).params, kind, params_file)
    return train_folder(kind, params, data, out, lambda msg: print(msg, file=sys.stderr))  # type: ignore[arg-type]


def test_only_train_and_val_reach_the_model(tmp_path: Path, params_file: Path) -> None:
    # given: two folders that differ only in their test split
    a = write_split(tmp_path / "a" / "30", test_seed=2)
    b = write_split(tmp_path / "b" / "30", test_seed=9)
    # when: training on each
    run("fnn", a, tmp_path / "out-a", params_file)
    run("fnn", b, tmp_path / "out-b", params_file)
    # then: same data hash, same scaling statistics, same weights
    ca, cb = load_checkpoint(tmp_path / "out-a"), load_checkpoint(tmp_path / "out-b")
    assert ca["train_data_sha256"] == cb["train_data_sha256"]
    for part in ("preprocessing", "state_dict"):
        assert all(torch.equal(ca[part][k], cb[part][k]) for k in ca[part])


def test_empty_validation_split_is_reported(tmp_path: Path, params_file: Path, capsys) -> None:
    # given: a folder whose validation split has no rows
    data = write_split(tmp_path / "30", val_rows=False)
    # when: training a network
    metrics = run("fnn", data, tmp_path / "out", params_file)
    # then: all epochs run, no validation loss, and the log says why
    assert metrics["epochs_run"] == 4
    assert metrics["best_val_loss"] is None
    assert "no early stopping" in capsys.readouterr().err


def test_no_training_rows_names_the_folder(tmp_path: Path, params_file: Path) -> None:
    # given: a folder whose training split is empty
    data = write_split(tmp_path / "processed" / "75")
    make_frame(1).iloc[:0].to_parquet(data / "train.parquet", index=False)
    # when / then
    with pytest.raises(ValueError, match=r"processed/75.*no rows"):
        run("fnn", data, tmp_path / "out", params_file)
