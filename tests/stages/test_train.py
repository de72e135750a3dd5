"""The train stage's command line: its three output files, a bad model kind."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest
import typer
from typer.testing import CliRunner

from pipeline.modelling.checkpoint import load_checkpoint
from pipeline.stages import choose, train
from tests.modelling.folders import PARAMS, write_split


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


def test_unknown_model_is_rejected(tmp_path: Path, params_file: Path) -> None:
    # given: a valid folder
    data = write_split(tmp_path / "30")
    # when: asking for a model kind that does not exist
    result = invoke("gru", str(data), str(tmp_path / "out"), "--params", str(params_file))
    # then: a usage error naming the valid kinds
    assert result.exit_code != 0
    assert "ls, fnn, lstm" in result.output


def test_the_choose_stage_makes_one_choice_that_every_angle_trains_on(
    tmp_path: Path, params_file: Path
) -> None:
    # given: two processed angle folders, and the trained angles in params
    root = tmp_path / "processed"
    write_split(root / "0", train_seed=0)
    write_split(root / "15", train_seed=5)
    params_file.write_text(params_file.read_text() + "train:\n  angles: [0, 15]\n")
    choice_file = tmp_path / "choices" / "ls.json"
    # when: choosing ls's inputs, then training each angle on the choice
    app = typer.Typer()
    app.command()(choose.main)
    chosen = CliRunner().invoke(app, ["ls", str(root), str(choice_file), "--params", str(params_file)])
    assert chosen.exit_code == 0, chosen.output
    for angle in ("0", "15"):
        out = tmp_path / "models" / "ls" / angle
        args = ["ls", str(root / angle), str(out), "--choice", str(choice_file), "--params", str(params_file)]
        result = invoke(*args)
        assert result.exit_code == 0, result.output
    # then: the file holds the decision, not the scores (new data at one angle must not retrain the
    # others unless the decision changes); both checkpoints read that kind, each with its own scores
    doc = json.loads(choice_file.read_text())["choice"]
    assert "scores" not in doc and doc["folds"].endswith("at each of 2 angles, scores averaged")
    own = []
    for angle in ("0", "15"):
        ck = load_checkpoint(tmp_path / "models" / "ls" / angle)
        assert ck["inputs"]["kind"] == doc["chosen"]
        assert {k: ck["inputs_choice"][k] for k in doc} == doc
        own.append(ck["inputs_choice"]["scores"])
    assert own[0] != own[1] and set(own[0]) == set(own[1])
