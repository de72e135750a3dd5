"""End to end, a unit swap: train on the small rig's units; calibrate its new unit from one insertion per
angle; score the new unit's held-out batch through its calibration; a client for it applies it; a client
for a unit without one gives force but no cues."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pandas as pd
import pytest

from needlecue_client import ForceClient, UncalibratedUnit
from pipeline.metrics.document import read_evaluation
from pipeline.modelling.prediction_store import Predictions
from tests.projects import SMALL_SIM, copy_registered, first_external_trial

pytestmark = pytest.mark.slow

TRAINING, D = SMALL_SIM["units"], SMALL_SIM["new_units"][0]  # D: the new unit, with its calibration batch


def test_a_new_unit_is_calibrated_scored_and_served(tiny_registered, tmp_path, monkeypatch):
    # Given the small project (the simulator records with the training units, and D with a calibration
    # batch), built through every stage and registered (shared: tests/conftest.py)
    root, _ = copy_registered(tiny_registered, tmp_path, monkeypatch)
    # Then D's calibration trials are in no split, only in processed/calibration
    manifest = json.loads((root / "data" / "processed" / "manifest.json").read_text())
    assert manifest["units"][D]["role"] == "new"
    assert {manifest["units"][u]["role"] for u in TRAINING} == {"training"}
    for angle in ("15", "45"):
        cal = pd.read_parquet(root / "data" / "processed" / "calibration" / f"{angle}.parquet")
        assert set(cal.unit_id) == {D} and len(cal)
        for split in ("train", "val", "test", "external"):
            frame = pd.read_parquet(root / "data" / "processed" / angle / f"{split}.parquet")
            assert not set(frame.batch_id) & set(cal.batch_id)
    # And D's held-out batch is scored as a calibrated unit, next to the training units
    metrics = read_evaluation(root / "reports" / "evaluation.json")
    assert metrics.by_unit[D].calibrated is True
    assert {metrics.by_unit[u].role for u in TRAINING if u in metrics.by_unit} == {"training"}
    assert set(metrics.calibration[D].angles_used) == {"15", "45"}
    assert metrics.unit_transfer["champion"].new_calibrated is not None
    # And the report has the section
    assert "## Estimator units" in (root / "reports" / "report.md").read_text()

    # When a simulator asks for the 15° champion for unit D
    monkeypatch.chdir(root)  # the store is the copy's (MLFLOW_TRACKING_URI: copy_registered)
    cache = tmp_path / "cache"
    client = ForceClient.from_registry(15, unit_id=D, cache_dir=cache, poll_s=None)
    # Then it is calibrated and gives the force the pipeline scored for D's held-out trial
    assert client.calibrated and client.has_cues
    rows = first_external_trial(root, "15", D)
    expected = Predictions(root / "data" / "predictions").get(client.kind, "15", "15", "external")
    client.reset()
    got = np.array(
        [
            client.step(v, t).force_n
            for v, t in zip(rows[list(client.channels)].to_numpy(), rows.t_s, strict=True)
        ]
    )
    np.testing.assert_allclose(got, expected[rows.index.to_numpy()], atol=1e-4)

    # When a simulator asks for the champion for a unit that has no calibration
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        stranger = ForceClient.from_registry(15, unit_id="unit-x", cache_dir=cache, poll_s=None)
    # Then it warns, gives force, and never a cue
    assert any(issubclass(w.category, UncalibratedUnit) for w in caught)
    assert not stranger.calibrated and not stranger.has_cues
    volts = rows[list(stranger.channels)].to_numpy()
    frames = [stranger.step(v, t) for v, t in zip(volts, rows.t_s, strict=True)]
    assert all(f.cue is None for f in frames) and all(np.isfinite(f.force_n).all() for f in frames)
