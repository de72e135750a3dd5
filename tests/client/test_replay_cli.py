"""`needlecue replay`: a recorded trial through the 30° champion and the unit's calibration, printed
and plotted."""

from __future__ import annotations

from pathlib import Path

import pytest
from typer.testing import CliRunner

from pipeline import client as fc
from pipeline.cli import app
from tests.client.builders import UNREACHABLE, Registered, cue_trials, register_unit, unit_document

pytestmark = pytest.mark.filterwarnings("ignore::pipeline.client.force.UncalibratedUnit")


def test_replay_command_prints_the_summary_and_writes_the_plot(
    registered: Registered, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # given: a processed parquet of two trials at 45°, recorded by a unit calibrated with the 30°
    # champion, the registry and an empty model cache
    data = tmp_path / "external.parquet"
    cue_trials(45, 2, "held", seed=3).to_parquet(data)
    register_unit(registered.uri, unit_document("est-r1", {30: registered.checkpoint}))
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
