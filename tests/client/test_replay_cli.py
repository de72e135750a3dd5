"""`needlecue replay`: a recorded trial through the 30° champion and the unit's calibration, printed
and plotted."""

from __future__ import annotations

from pathlib import Path

import pytest
from typer.testing import CliRunner

import needlecue_client as fc
from pipeline.cli import app
from tests.client.builders import (
    UNREACHABLE,
    Registered,
    cue_evidence,
    cue_trials,
    register_unit,
    unit_document,
)

pytestmark = pytest.mark.filterwarnings("ignore::needlecue_client.force.UncalibratedUnit")


def test_replay_command_prints_the_summary_and_writes_the_plot(
    registered: Registered, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # given: a processed parquet of two trials at 45°, recorded by a unit calibrated with the 30°
    # champion, the registry and an empty model cache
    data = tmp_path / "external.parquet"
    cue_trials(45, 2, "held", seed=3).to_parquet(data)
    doc = unit_document("est-r1", {30: registered.checkpoint}, cues=cue_evidence(registered.pack))
    register_unit(registered.uri, doc)
    monkeypatch.setenv("MLFLOW_TRACKING_URI", registered.uri)
    monkeypatch.setenv(fc.CACHE_ENV, str(tmp_path / "cache"))
    runner = CliRunner()
    # when: replaying the second trial against the 30° champion, as that unit
    png = tmp_path / "plot.png"
    result = runner.invoke(
        app,
        [
            "replay",
            str(data),
            "--angle",
            "30",
            "--trial",
            "held/t01",
            "--unit-id",
            "est-r1",
            "--out",
            str(png),
        ],
    )
    # then: exit 0, the model and the unit's calibration named, a timeline that waits for the rest
    # reading, then says to correct the angle (45° is 15° off the preset), the RMSE per axis and a PNG
    assert result.exit_code == 0, result.output
    lines = result.output.splitlines()
    assert lines[0] == "held/t01: 90 samples through needle-force-30 v1 (lstm), preset angle 30°"
    assert lines[1] == "unit est-r1: calibrated (needle-unit-est-r1 v1)"
    timeline = [line.split()[2] for line in lines[2:-2]]
    assert timeline == ["wait", "correct"], result.output
    assert "angle    45°" in lines[-3]
    assert "RMSE vs reference: fx" in result.output and f"wrote {png}" in result.output
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    # when: a unit that was never calibrated
    unknown = runner.invoke(
        app, ["replay", str(data), "--angle", "30", "--unit-id", "est-r9", "--out", str(tmp_path / "u.png")]
    )
    # then: the force all the same, no cues, and why, with the fix
    assert unknown.exit_code == 0, unknown.output
    assert "uncalibrated: it has no registered calibration (needle-unit-est-r9@current)" in unknown.output
    assert "no cues: the unit is not calibrated for this model" in unknown.output
    assert "needlecue calibrate BATCH_DIR" in unknown.output  # the warning's fix

    # when: bad inputs: an unknown trial, a model for another angle, an unreachable registry with no copy
    bad_trial = runner.invoke(app, ["replay", str(data), "--angle", "30", "--trial", "held/t09"])
    wrong_angle = runner.invoke(
        app,
        [
            "replay",
            str(data),
            "--angle",
            "45",
            "--model-dir",
            str(tmp_path / "cache/needle-force-30/champion"),
        ],
    )
    monkeypatch.setenv("MLFLOW_TRACKING_URI", UNREACHABLE)
    offline = runner.invoke(app, ["replay", str(data), "--angle", "15"])
    # then: exit 1 for bad input, 2 for the registry, each with a message saying what
    assert (bad_trial.exit_code, wrong_angle.exit_code, offline.exit_code) == (1, 1, 2)
    assert "no trial 'held/t09'" in bad_trial.output and "held/t00, held/t01" in bad_trial.output
    assert "--angle 45 but the model" in wrong_angle.output
    assert "needle-force-15@champion" in offline.output and "no local copy" in offline.output


@pytest.mark.parametrize("form", ["csv", "tdms"])
def test_replay_takes_a_raw_trial_and_its_unit_from_the_batch_folder(
    registered: Registered, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, form: str
) -> None:
    # given: a raw rig-log/1 batch of one trial at 30°, recorded by unit est-r1 (calibrated with the
    # 30° champion), as CSV files or as a TDMS reference stream (written by npTDMS) beside a
    # gzip-compressed estimator stream; the registry and an empty model cache
    from pipeline.config import SimulateParams
    from pipeline.sim.rig import BatchPlan, write_batch
    from tests.rig.batches import gzip_file, to_tdms

    raw = tmp_path / "raw"
    raw.mkdir()
    write_batch(SimulateParams(), BatchPlan("lab-r1", 1, (30.0,), 1, 1, "est-r1"), raw)
    doc = unit_document("est-r1", {30: registered.checkpoint}, cues=cue_evidence(registered.pack))
    register_unit(registered.uri, doc)
    monkeypatch.setenv("MLFLOW_TRACKING_URI", registered.uri)
    monkeypatch.setenv(fc.CACHE_ENV, str(tmp_path / "cache"))
    monkeypatch.chdir(Path(__file__).resolve().parents[2])  # params.yaml of the project
    fsr_file = next((raw / "lab-r1").glob("*.fsr.csv"))
    trial = fsr_file.name.removesuffix(".fsr.csv")
    given = fsr_file
    if form == "tdms":
        gzip_file(fsr_file)
        given = to_tdms(fsr_file.with_name(f"{trial}.ref.csv"), time="waveform")
    png = tmp_path / "raw.png"
    # when: replaying the raw trial file, with no --unit-id
    result = CliRunner().invoke(app, ["replay", str(given), "--angle", "30", "--out", str(png)])
    # then: it is ingested and resampled like the pipeline does, and the unit comes from batch.yaml
    assert result.exit_code == 0, result.output
    assert result.output.startswith(f"lab-r1/{trial}: ")
    assert "unit est-r1: calibrated (needle-unit-est-r1 v1)" in result.output
    assert png.is_file()


@pytest.mark.parametrize("name", ["notes.txt", "t001.csv"])
def test_replay_of_something_else_is_a_clear_error(tmp_path: Path, name: str) -> None:
    # given: a file that is neither a processed parquet, a rig-log/1 trial file nor a batch folder
    path = tmp_path / name
    path.write_text("t_ms,a\n1,2\n")
    # when / then: exit 1 naming what replay takes, not "Parquet magic bytes not found"
    result = CliRunner().invoke(app, ["replay", str(path), "--angle", "30"])
    assert result.exit_code == 1
    assert "not a processed parquet file, a rig-log/1 trial file" in result.output


def test_replay_of_a_raw_trial_whose_reference_cannot_be_aligned_plays_the_estimator_stream(
    registered: Registered, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # given: a raw batch of one trial at 30° whose reference is stamped 2 s late (a shifted clock:
    # resample sets it aside), recorded by a calibrated unit
    import pandas as pd

    from pipeline.config import SimulateParams
    from pipeline.sim.rig import BatchPlan, write_batch

    raw = tmp_path / "raw"
    raw.mkdir()
    write_batch(SimulateParams(), BatchPlan("lab-r2", 1, (30.0,), 1, 1, "est-r1"), raw)
    register_unit(
        registered.uri,
        unit_document("est-r1", {30: registered.checkpoint}, cues=cue_evidence(registered.pack)),
    )
    monkeypatch.setenv("MLFLOW_TRACKING_URI", registered.uri)
    monkeypatch.setenv(fc.CACHE_ENV, str(tmp_path / "cache"))
    monkeypatch.chdir(Path(__file__).resolve().parents[2])
    fsr_file = next((raw / "lab-r2").glob("*.fsr.csv"))
    ref_file = fsr_file.with_name(fsr_file.name.replace(".fsr.", ".ref."))
    ref = pd.read_csv(ref_file)
    ref.assign(t_s=ref["t_s"] + 2.0).to_csv(ref_file, index=False, float_format="%.6f")
    # when: replaying the raw trial file
    result = CliRunner().invoke(
        app, ["replay", str(fsr_file), "--angle", "30", "--out", str(tmp_path / "r.png")]
    )
    # then: exit 0, a warning naming why, the force and cues of the estimator stream, and no RMSE
    assert result.exit_code == 0, result.output
    assert "its reference could not be aligned (shifted clock: " in result.output
    assert "replaying the estimator stream alone, no RMSE" in result.output
    assert "unit est-r1: calibrated" in result.output
    assert "RMSE vs reference: no reference force" in result.output
    assert (tmp_path / "r.png").is_file()
