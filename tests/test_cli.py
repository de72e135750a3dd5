"""The `needlecue` commands a person runs by hand."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import yaml
from typer.testing import CliRunner

from pipeline.cli import app
from tests.rig.batches import gzip_file, lines_of, write_lines

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
    # and every trial is accounted for
    folder = tmp_path / "raw" / "lab-bench-a"
    assert f"lab-bench-a ({folder}): 3 trial(s), 2 pass ingest's checks, 1 set aside" in bad.output
    assert "  t001: passes ingest\n" in bad.output
    assert "  t002: set aside at ingest (problems above)\n" in bad.output


def test_check_says_where_the_last_run_placed_each_trial(tmp_path, monkeypatch):
    # Given a project whose last run's ledger placed t001 in training and set t003 aside at resample
    shutil.copytree(LAB_BATCH, tmp_path / "data" / "raw" / "lab-bench-a")
    monkeypatch.chdir(tmp_path)
    ledger = Path("reports/ledger/ledger.json")
    ledger.parent.mkdir(parents=True)
    src = "data/raw/lab-bench-a"
    entries = [
        {
            "batch_id": "lab-bench-a",
            "trial_id": "t001",
            "source": src,
            "outcome": "used",
            "angle": "30",
            "use": "train",
        },
        {
            "batch_id": "lab-bench-a",
            "trial_id": "t003",
            "source": src,
            "outcome": "set aside",
            "stage": "resample",
            "where": [{"file": f"{src}/t003.*", "reason": "reference stream is constant"}],
        },
    ]
    ledger.write_text(json.dumps({"entries": entries}))
    # When the raw folder is checked from the project folder
    result = runner.invoke(app, ["check", "data/raw", "--params", "none.yaml"])
    # Then each trial known to the ledger says where it ended up
    assert result.exit_code == 0, result.output
    assert "  t001: passes ingest; last dvc repro: used: train at 30°\n" in result.output
    assert (
        f"  t003: passes ingest; last dvc repro: set aside at resample: {src}/t003.*: reference stream"
        in result.output
    )
    assert "  t002: passes ingest\n" in result.output


def test_check_names_a_batch_copied_under_another_name(tmp_path):
    # Given a batch and a copy of it under another batch id
    shutil.copytree(LAB_BATCH, tmp_path / "raw" / "lab-bench-a")
    copy = shutil.copytree(LAB_BATCH, tmp_path / "raw" / "lab-bench-z")
    (copy / "batch.yaml").write_text((copy / "batch.yaml").read_text().replace("lab-bench-a", "lab-bench-z"))
    # When checked
    result = runner.invoke(app, ["check", str(tmp_path / "raw"), "--params", str(tmp_path / "none.yaml")])
    # Then each copied trial names the one it repeats, and the check fails
    assert result.exit_code == 1
    assert (
        "  t002: passes ingest, but its samples are those of lab-bench-a/t002: split will set it aside"
        in result.output
    )
    assert "3 trial(s) repeat another's recording" in result.output


def test_check_names_a_trial_copied_with_its_timestamps_shifted_or_compressed(tmp_path):
    # Given a batch, a copy of it with every timestamp 1 s later, and one with a gzip-compressed trial
    shutil.copytree(LAB_BATCH, tmp_path / "raw" / "lab-bench-a")
    shifted = shutil.copytree(LAB_BATCH, tmp_path / "raw" / "lab-bench-s")
    (shifted / "batch.yaml").write_text(
        (shifted / "batch.yaml").read_text().replace("lab-bench-a", "lab-bench-s")
    )
    for trial in ("t001", "t002", "t003"):
        for name, col, step in ((f"{trial}.fsr.csv", 0, 1000.0), (f"{trial}.ref.csv", 0, 1.0)):
            rows = lines_of(shifted / name)
            out = [rows[0]]
            for r in rows[1:]:
                cells = r.split(",")
                cells[col] = f"{float(cells[col]) + step:.3f}"
                out.append(",".join(cells))
            write_lines(shifted / name, out)
    gz = shutil.copytree(LAB_BATCH, tmp_path / "raw" / "lab-bench-g")
    (gz / "batch.yaml").write_text((gz / "batch.yaml").read_text().replace("lab-bench-a", "lab-bench-g"))
    gzip_file(gz / "t001.fsr.csv")
    # When checked
    result = runner.invoke(app, ["check", str(tmp_path / "raw"), "--params", str(tmp_path / "none.yaml")])
    # Then the shifted and the compressed copies name the original, as split would set them aside
    assert result.exit_code == 1
    assert "  t001: passes ingest, but its samples are those of lab-bench-a/t001" in result.output
    assert result.output.count("but its samples are those of lab-bench-a/") == 6


def test_check_refuses_a_missing_folder(tmp_path):
    result = runner.invoke(app, ["check", str(tmp_path / "nope")])
    assert result.exit_code == 2
    assert "not a folder" in result.output


def test_simulate_writes_batches_and_never_clears_a_foreign_folder(tmp_path):
    # Given a small params file
    params = tmp_path / "params.yaml"
    small = {
        "angles_deg": [30],
        "train_batches": 1,
        "trials_per_angle": 1,
        "heldout_trials_per_angle": 1,
        "units": ["est-sim-001"],
        "new_units": [],
    }
    params.write_text(yaml.safe_dump({"simulate": small}))
    # When simulating into a new folder, then into a folder holding other data
    ok = runner.invoke(app, ["simulate", str(tmp_path / "sim"), "--params", str(params)])
    (tmp_path / "lab").mkdir()
    (tmp_path / "lab" / "keep.csv").write_text("x\n")
    refused = runner.invoke(app, ["simulate", str(tmp_path / "lab"), "--params", str(params)])
    # Then the first writes rig-log/1 batches and the second refuses, touching nothing
    assert ok.exit_code == 0, ok.output
    assert (tmp_path / "sim" / "sim-tissue-1-est-sim-001" / "batch.yaml").is_file()
    assert refused.exit_code == 2 and "not written by the simulator" in refused.output
    assert (tmp_path / "lab" / "keep.csv").read_text() == "x\n"


def test_a_typo_in_params_fails_loudly(tmp_path):
    params = tmp_path / "params.yaml"
    params.write_text("simulate:\n  trails_per_angle: 3\n")
    result = runner.invoke(app, ["simulate", str(tmp_path / "sim"), "--params", str(params)])
    assert result.exit_code != 0
    assert "trails_per_angle" in str(result.exception)


# --- needlecue calibrate ---------------------------------------------------------------------------


def break_cell(fsr: Path) -> None:
    """Text in the first channel of the fourth sample (line 5)."""
    lines = fsr.read_text().splitlines()
    cells = lines[4].split(",")
    lines[4] = ",".join([cells[0], "oops", *cells[2:]])
    fsr.write_text("\n".join(lines) + "\n")


def test_calibrate_refuses_a_batch_with_nothing_usable_naming_file_and_line(tmp_path):
    # Given a batch whose every trial has text in a number column
    batch = tmp_path / "lab-bench-a"
    shutil.copytree(LAB_BATCH, batch)
    for fsr in sorted(batch.glob("*.fsr.csv")):
        break_cell(fsr)
    # When calibrating from it
    result = runner.invoke(app, ["calibrate", str(batch), "--params", str(tmp_path / "none.yaml")])
    # Then exit 1, each problem located as file:line, and nothing usable said
    assert result.exit_code == 1, result.output
    for trial in ("t001", "t002", "t003"):
        assert f"{trial}.fsr.csv:5" in result.output
    assert "nothing usable" in result.output
    missing = runner.invoke(app, ["calibrate", str(tmp_path / "nope")])
    assert missing.exit_code == 2 and "not a folder" in missing.output


def test_calibrate_registers_a_new_unit_through_the_champions(tmp_path, mlflow_store):
    # Given LS champions at 30° and 45° (registered with their checkpoints, as the register stage
    # does), and a short simulated calibration batch of a new unit at 30° only
    from needlecue_client import ForceClient
    from pipeline.modelling.fit import fit
    from tests.client.builders import TINY, cue_trials, register

    for angle in (30, 45):
        checkpoint = fit("ls", TINY["ls"], cue_trials(angle, 2)).checkpoint
        register(mlflow_store, tmp_path, checkpoint, angle=angle, with_checkpoint=True)
    none = str(tmp_path / "none.yaml")
    made = runner.invoke(
        app,
        [
            *("simulate-batch", str(tmp_path / "raw"), "cal-101"),
            *("--purpose", "calibration", "--unit", "est-sim-101", "--angles", "30", "--trials", "1"),
            *("--params", none),
        ],
    )
    assert made.exit_code == 0, made.output
    batch = str(tmp_path / "raw" / "cal-101")
    # When: a dry run, a run naming another unit, then the real run
    dry = runner.invoke(app, ["calibrate", batch, "--params", none, "--dry-run"])
    other = runner.invoke(app, ["calibrate", batch, "--params", none, "--unit-id", "est-sim-999"])
    real = runner.invoke(app, ["calibrate", batch, "--params", none, "--unit-id", "est-sim-101"])
    # Then the dry run prints the fit and registers nothing, another unit is refused, and the real run
    # registers version 1 @current
    assert dry.exit_code == 0, dry.output
    assert "dry run: needle-unit-est-sim-101 not registered" in dry.output
    assert other.exit_code == 1 and "recorded by unit 'est-sim-101'" in other.output
    assert real.exit_code == 0, real.output
    assert "registered: needle-unit-est-sim-101 version 1 (@current)" in real.output
    loss = next(line for line in real.output.splitlines() if line.startswith("  ls: loss"))
    before, after = (float(x) for x in loss.split()[2:5:2])
    assert after < before
    assert "angles used: 30; missing: 45" in real.output
    # And the simulator's client of that unit is calibrated at both angles: one LS transform serves the
    # LS champions, 45° without a calibration trial too
    for angle in (30, 45):
        client = ForceClient.from_registry(angle, unit_id="est-sim-101", cache_dir=tmp_path / "cache")
        assert client.calibrated and client.calibration["version"] == "1"
    # And a batch recorded for training is calibrated from only with a warning
    runner.invoke(
        app,
        [
            *("simulate-batch", str(tmp_path / "raw"), "train-101", "--unit", "est-sim-101"),
            *("--angles", "30", "--trials", "1", "--params", none),
        ],
    )
    training = runner.invoke(
        app, ["calibrate", str(tmp_path / "raw" / "train-101"), "--params", none, "--dry-run"]
    )
    assert training.exit_code == 0, training.output
    assert "purpose 'training', not 'calibration'" in training.output
