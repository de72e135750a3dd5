"""End to end on rigs the defaults were not built on (issue 24): training units of one member of the
simulator's family, a new unit of another, with and without their circuits declared. Every feature
that needs a circuit takes the unit's own; the inputs are chosen on the data; the client serving the
new unit computes what the pipeline scored."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
import yaml

from needlecue_client import ForceClient
from needlecue_runtime.features import InputTransform
from needlecue_runtime.frontend import declared
from pipeline.config import SimulateParams
from pipeline.metrics.document import read_evaluation
from pipeline.modelling.checkpoint import load_checkpoint
from pipeline.modelling.prediction_store import Predictions
from pipeline.modelling.predictor import load_predictor
from pipeline.sim import rig, rigs
from tests.projects import SWAP_SIM, A, B, C, D, first_external_trial, make_project, run, use_small_models

pytestmark = pytest.mark.slow

TRAINING_RIG, NEW_RIG = "transimpedance", "divider-3v3-ground"
# units A, B, C record with the training rig; D's batches come from another design (written below)
SIM = {**SWAP_SIM, "rig": TRAINING_RIG, "calibration_trials_per_angle": 0, "new_units": []}


def _project(tmp_path, declare: bool, pin: str | None):
    """The small project on the training rig, and unit D's held-out and calibration batches recorded
    with another design and dropped into data/raw as a lab would."""
    root = make_project(tmp_path / "proj", {**SIM, "declare_front_end": declare})
    params = use_small_models(root)
    for model in ("ls", "fnn"):
        params[model]["inputs"]["kind"] = pin or "auto"
    (root / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    other = SimulateParams(**{**SIM, "rig": NEW_RIG, "declare_front_end": declare})
    raw = root / "data" / "raw"
    rig.write_new_batch(other, raw, "lab2-heldout-d", (15.0, 45.0), 2, unit_id=D)
    rig.write_new_batch(other, raw, "lab2-calib-d", (15.0, 45.0), 1, unit_id=D, purpose="calibration")
    run(root, "dvc", "repro")
    return root


def _client_reproduces_the_scored_force(
    root, tmp_path, monkeypatch
) -> tuple[ForceClient, pd.DataFrame, np.ndarray]:
    monkeypatch.chdir(root)  # the store is the project's (MLFLOW_TRACKING_URI from the test fixture)
    client = ForceClient.from_registry(15, unit_id=D, cache_dir=tmp_path / "cache", poll_s=None)
    assert client.calibrated
    rows = first_external_trial(root, "15", D)
    expected = Predictions(root / "data" / "predictions").get(client.kind, "15", "15", "external")
    client.reset()
    volts = rows[list(client.channels)].to_numpy()
    got = np.array([client.step(v, t).force_n for v, t in zip(volts, rows.t_s, strict=True)])
    np.testing.assert_allclose(got, expected[rows.index.to_numpy()], atol=1e-4)
    return client, rows, got


def test_a_new_unit_of_another_design_is_read_through_its_own_declared_circuit(tmp_path, monkeypatch):
    # Given training units of the op-amp design and a new unit D built with a 3.3 V ground-side
    # divider, each batch declaring its circuit; the inputs left to the data
    root = _project(tmp_path, declare=True, pin=None)
    training = rigs.declared_front_end(rigs.rig(TRAINING_RIG)).model_dump(mode="json")
    new = rigs.declared_front_end(rigs.rig(NEW_RIG)).model_dump(mode="json")
    # Then each unit's circuit is next to its rows, as its batches declare it
    circuits = json.loads((root / "data" / "processed" / "15" / "front_ends.json").read_text())
    assert circuits == {A: training, B: training, C: training, D: new}
    # and the models chose among the inputs that can read D at all: the FSR's conductance, through
    # the training units' circuit; D's calibration records its own
    for kind in ("ls", "fnn"):
        ck = load_checkpoint(root / "models" / kind / "15")
        assert ck["inputs"]["front_end"] == training
        assert ck["inputs_choice"]["only"] == f"the conductance kinds: {D} declares another circuit"
        assert set(ck["inputs_choice"]["scores"]) == {"conductance", "rest_conductance"}
    # and through its own circuit and calibration, D's force is within the target of the same units'
    transfer = read_evaluation(root / "reports" / "evaluation.json").unit_transfer["champion"]
    assert transfer.new_calibrated is not None and transfer.same_unit is not None
    assert transfer.new_calibrated <= 1.2 * transfer.same_unit
    doc = json.loads((root / "data" / "calibration" / f"{D}.json").read_text())
    assert doc["front_end"] == new
    # and the cue packs say which circuit their directions are in
    assert json.loads((root / "reports" / "cues" / "packs" / "15.json").read_text())["front_end"] == training
    # and the report says what the models read, through which circuit
    report = (root / "reports" / "report.md").read_text()
    assert "## What the models read" in report and "transimpedance 1 V, 47 kΩ" in report
    assert f"candidates: the conductance kinds: {D} declares another circuit" in report
    # When a simulator serves D, then it reads D through D's circuit: the force the pipeline scored
    client, rows, got = _client_reproduces_the_scored_force(root, tmp_path, monkeypatch)
    # which is not what the training units' circuit would give
    predictor = load_predictor(root / "models" / client.kind / "15")
    # (D's calibration, a map on its conductance, read as if D had the training units' circuit too)
    transform = InputTransform.from_dict(doc["transforms"][client.kind], declared(training))
    wrong = predictor.predict(rows.drop(columns=["fx", "fy", "fz"]), transform)
    assert not np.allclose(wrong, got, atol=1e-3)


def test_with_no_circuit_declared_nothing_assumes_one_and_the_inputs_are_chosen_on_the_data(
    tmp_path, monkeypatch
):
    # Given the same rigs, but no batch declares its circuit, and the inputs left to the data
    root = _project(tmp_path, declare=False, pin=None)
    # Then no circuit is recorded anywhere, and each model's inputs were chosen among the volts kinds
    circuits = json.loads((root / "data" / "processed" / "45" / "front_ends.json").read_text())
    assert circuits == {A: None, B: None, C: None, D: None}
    for kind in ("ls", "fnn"):
        ck = load_checkpoint(root / "models" / kind / "45")
        choice = ck["inputs_choice"]
        assert set(choice["scores"]) == {"volts", "rest_volts"}
        assert choice["folds"].startswith("leave-one-unit-out (3 units)")
        assert ck["inputs"] == {"kind": choice["chosen"], "rest_s": 0.5, "front_end": None}
    assert json.loads((root / "reports" / "cues" / "packs" / "45.json").read_text())["front_end"] is None
    doc = json.loads((root / "data" / "calibration" / f"{D}.json").read_text())
    assert doc["front_end"] is None
    report = (root / "reports" / "report.md").read_text()
    assert "| validation |" in report and "conductance (%)" not in report
    # And a simulator serving D computes what the pipeline scored
    _client_reproduces_the_scored_force(root, tmp_path, monkeypatch)
