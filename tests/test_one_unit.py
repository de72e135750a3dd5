"""End to end, the paper's lab: one training unit of a family member, later replaced by a new unit
calibrated from one insertion per angle, with the circuit declared and without (issue 39).

With one training unit nothing says how far another unit sits from it: the new unit gets no angle cue
until it is calibrated, and its calibration insertions then move the estimator's classes to it. Where
the circuit is declared, its calibration is a map on the FSRs' conductance; where not, on the inputs."""

from __future__ import annotations

import json

import numpy as np
import pytest

from needlecue_client import ForceClient
from pipeline.metrics.document import read_evaluation
from pipeline.modelling.prediction_store import Predictions
from tests.projects import SWAP_SIM, A, D, first_external_trial, make_project, run, use_small_models

pytestmark = pytest.mark.slow

RIG = "divider-3v3-ground"  # a member of the simulator's family the defaults were not built on
SIM = {**SWAP_SIM, "rig": RIG, "units": [A], "train_batches": 2, "trials_per_angle": 3, "new_units": [D]}


@pytest.mark.parametrize("declare", [True, False], ids=["circuit-declared", "no-circuit"])
def test_one_training_unit_then_a_new_unit_after_one_calibration_insertion_per_angle(
    tmp_path, monkeypatch, declare: bool
):
    # Given: a project whose simulator records one training unit A, and a new unit D with its
    # calibration batch, the circuit in batch.yaml or not
    root = make_project(tmp_path / "proj", {**SIM, "declare_front_end": declare})
    use_small_models(root)
    # When: the whole pipeline runs
    run(root, "dvc", "repro")
    # Then: D's calibration acts on the FSRs' conductance where the circuit is declared, else on the
    # model's inputs
    doc = json.loads((root / "data" / "calibration" / f"{D}.json").read_text())
    assert {t["domain"] for t in doc["transforms"].values()} == {"conductance" if declare else "inputs"}
    # And: uncalibrated, D is shown no angle cue (only a force check can stop it); calibrated, its cues
    # are scored as the trainee sees them, within the wrong-cue limit
    cues = read_evaluation(root / "reports" / "evaluation.json").cues["ls"]
    uncal, cal = cues["new_uncalibrated"], cues["new_calibrated"]
    assert uncal.coverage_frames is not None and cal.coverage_frames is not None
    assert uncal.coverage_frames <= cal.coverage_frames and uncal.wrong_final == 0.0
    report = (root / "reports" / "report.md").read_text()
    assert "What a trainee sees" in report and "no angle cue" in report

    # When: a simulator serves unit D, and another serves a unit without a calibration
    monkeypatch.chdir(root)  # the store is the project's (MLFLOW_TRACKING_URI from the test fixture)
    cache = tmp_path / "cache"
    client = ForceClient.from_registry(15, unit_id=D, cache_dir=cache, poll_s=None)
    with pytest.warns(UserWarning):
        stranger = ForceClient.from_registry(
            15, unit_id="unit-x", cache_dir=cache, poll_s=None, cues_uncalibrated=True
        )
    rows = first_external_trial(root, "15", D)
    expected = Predictions(root / "data" / "predictions").get(client.kind, "15", "15", "external")
    for c in (client, stranger):
        c.reset()
    volts, times = rows[list(client.channels)].to_numpy(), rows.t_s.to_numpy()
    ours = [client.step(v, t) for v, t in zip(volts, times, strict=True)]
    theirs = [stranger.step(v, t) for v, t in zip(volts, times, strict=True)]
    # Then: D's client gives the force the pipeline scored for D, through its calibration, and its
    # calibration insertions tell the angle estimator where D's classes lie (with one training unit they
    # used to change nothing); nothing tells it where the stranger's lie
    assert client.calibrated and client.has_cues
    assert client.knows_unit and not stranger.knows_unit
    np.testing.assert_allclose([f.force_n for f in ours], expected[rows.index.to_numpy()], atol=1e-4)
    # And: the uncalibrated unit, cues asked for anyway, never gets an angle cue: it is told why
    assert {f.cue.cue for f in theirs} - {"wait", "stop"} == {"none"}
    assert {f.cue.no_cue for f in theirs if f.cue.cue == "none"} == {"uncalibrated"}
    assert all("force" in f.cue.reason for f in theirs if f.cue.cue == "stop")  # the force check only
