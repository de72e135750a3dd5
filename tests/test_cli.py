"""The `needlecue` commands a person runs by hand."""

from __future__ import annotations

import shutil
from pathlib import Path

import yaml
from typer.testing import CliRunner

from pipeline.cli import app

runner = CliRunner()
LAB_BATCH = Path(__file__).parent / "fixtures" / "rig-log" / "lab-bench-a"


def test_check_passes_a_good_folder_and_names_what_is_wrong_in_a_bad_one(tmp_path):
    # Given a good batch and a copy with text in a number column
    shutil.copytree(LAB_BATCH, tmp_path / "raw" / "lab-bench-a")
    good = runner.invoke(app, ["check", str(tmp_path / "raw"), "--params", str(tmp_path / "none.yaml")])
    fsr = tmp_path / "raw" / "lab-bench-a" / "t002.fsr.csv"
    lines = fsr.read_text().splitlines()
    lines[4] = lines[4].split(",", 1)[0] + ",oops" + "," + lines[4].split(",", 2)[2]
    fsr.write_text("\n".join(lines) + "\n")
    # When checked
    bad = runner.invoke(app, ["check", str(tmp_path / "raw"), "--params", str(tmp_path / "none.yaml")])
    # Then the good folder passes and the bad one fails, naming file, line and column
    assert good.exit_code == 0, good.output
    assert bad.exit_code == 1
    assert "t002.fsr.csv:5" in bad.output and "oops" in bad.output


def test_check_refuses_a_missing_folder(tmp_path):
    result = runner.invoke(app, ["check", str(tmp_path / "nope")])
    assert result.exit_code == 2
    assert "not a folder" in result.output


def test_simulate_writes_batches_and_never_clears_a_foreign_folder(tmp_path):
    # Given a small params file
    params = tmp_path / "params.yaml"
    small = {"angles_deg": [30], "train_batches": 1, "trials_per_angle": 1, "heldout_trials_per_angle": 1}
    params.write_text(yaml.safe_dump({"simulate": small}))
    # When simulating into a new folder, then into a folder holding other data
    ok = runner.invoke(app, ["simulate", str(tmp_path / "sim"), "--params", str(params)])
    (tmp_path / "lab").mkdir()
    (tmp_path / "lab" / "keep.csv").write_text("x\n")
    refused = runner.invoke(app, ["simulate", str(tmp_path / "lab"), "--params", str(params)])
    # Then the first writes rig-log/1 batches and the second refuses, touching nothing
    assert ok.exit_code == 0, ok.output
    assert (tmp_path / "sim" / "sim-tissue-1" / "batch.yaml").is_file()
    assert refused.exit_code == 2 and "not written by the simulator" in refused.output
    assert (tmp_path / "lab" / "keep.csv").read_text() == "x\n"


def test_a_typo_in_params_fails_loudly(tmp_path):
    params = tmp_path / "params.yaml"
    params.write_text("simulate:\n  trails_per_angle: 3\n")
    result = runner.invoke(app, ["simulate", str(tmp_path / "sim"), "--params", str(params)])
    assert result.exit_code != 0
    assert "trails_per_angle" in str(result.exception)
