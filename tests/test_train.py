"""The train stage's entry point: its three output files, its errors, what it reads."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest
import torch
import typer
from typer.testing import CliRunner

from pipeline import train
from pipeline.models import load_checkpoint
from tests.test_models import make_frame

PARAMS = """\
ls:
  fit_intercept: false
fnn:
  hidden: [6]
  max_epochs: 4
  patience: 2
  batch_size: 32
lstm:
  window: 4
  hidden: 5
  max_epochs: 3
  patience: 2
  batch_size: 32
"""


def write_split(data_dir: Path, train_seed: int = 0, val_rows: bool = True, test_seed: int = 2) -> Path:
    """A processed angle folder as the split stage writes it."""
    data_dir.mkdir(parents=True, exist_ok=True)
    val = make_frame(1, seed=1, batch_id="b2")
    make_frame(3, seed=train_seed).to_parquet(data_dir / "train.parquet", index=False)
    (val if val_rows else val.iloc[:0]).to_parquet(data_dir / "val.parquet", index=False)
    make_frame(1, seed=test_seed, batch_id="b3").to_parquet(data_dir / "test.parquet", index=False)
    make_frame(2, seed=3, batch_id="heldout").to_parquet(data_dir / "external.parquet", index=False)
    return data_dir


@pytest.fixture
def params_file(tmp_path: Path) -> Path:
    path = tmp_path / "params.yaml"
    path.write_text(PARAMS)
    return path


def invoke(*args: str) -> object:
    app = typer.Typer()
    app.command()(train.main)
    return CliRunner().invoke(app, list(args))


@pytest.mark.parametrize("kind", ["ls", "fnn", "lstm"])
def test_main_writes_model_metrics_and_history(kind: str, tmp_path: Path, params_file: Path) -> None:
    # given: a processed angle folder
    data = write_split(tmp_path / "processed" / "30")
    out = tmp_path / "models" / kind / "30"
    # when: running the stage's command line
    result = invoke(kind, str(data), str(out), "--params", str(params_file))
    # then: the three files, consistent with each other
    assert result.exit_code == 0, result.output
    assert load_checkpoint(out)["kind"] == kind
    metrics = json.loads((out / "train_metrics.json").read_text())
    expected = {"kind", "angle_deg", "epochs_run", "best_epoch", "best_val_loss", "n_train"}
    assert expected | {"n_val", "train_data_sha256"} <= metrics.keys()
    assert (metrics["kind"], metrics["angle_deg"], metrics["n_train"]) == (kind, 30.0, 120)
    assert "train_seconds" not in metrics  # wall time would make identical models hash differently
    with (out / "history.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert list(rows[0]) == ["epoch", "train_loss", "val_loss"]
    assert len(rows) == metrics["epochs_run"]


def test_only_train_and_val_reach_the_model(tmp_path: Path, params_file: Path) -> None:
    # given: two folders that differ only in their test split
    a = write_split(tmp_path / "a" / "30", test_seed=2)
    b = write_split(tmp_path / "b" / "30", test_seed=9)
    # when: training on each
    train.run("fnn", a, tmp_path / "out-a", params_file)
    train.run("fnn", b, tmp_path / "out-b", params_file)
    # then: same data hash, same scaling statistics, same weights
    ca, cb = load_checkpoint(tmp_path / "out-a"), load_checkpoint(tmp_path / "out-b")
    assert ca["train_data_sha256"] == cb["train_data_sha256"]
    for part in ("preprocessing", "state_dict"):
        assert all(torch.equal(ca[part][k], cb[part][k]) for k in ca[part])


def test_empty_validation_split_is_reported(tmp_path: Path, params_file: Path, capsys) -> None:
    # given: a folder whose validation split has no rows
    data = write_split(tmp_path / "30", val_rows=False)
    # when: training a network
    metrics = train.run("fnn", data, tmp_path / "out", params_file)
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
        train.run("fnn", data, tmp_path / "out", params_file)


def test_unknown_model_is_rejected(tmp_path: Path, params_file: Path) -> None:
    # given: a valid folder
    data = write_split(tmp_path / "30")
    # when: asking for a model kind that does not exist
    result = invoke("gru", str(data), str(tmp_path / "out"), "--params", str(params_file))
    # then: a usage error naming the valid kinds
    assert result.exit_code != 0
    assert "ls, fnn, lstm" in result.output
