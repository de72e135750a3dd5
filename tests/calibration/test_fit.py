"""A unit's input transform, fitted through frozen models."""

from __future__ import annotations

import numpy as np
import pandas as pd

from pipeline.calibration import fit as calibration_fit
from pipeline.calibration.fit import AngleData, fit_transform
from pipeline.calibration.unit import calibrate_unit
from pipeline.config import CalibrateParams
from pipeline.modelling.fit import fit
from pipeline.modelling.kinds.fnn import FNNParams
from pipeline.modelling.kinds.ls import LSParams
from tests.modelling.frames import CHANNELS, make_frame

P = CalibrateParams()


def _distorted(frame: pd.DataFrame, a: np.ndarray) -> pd.DataFrame:
    """The same trials read by a unit whose channels mix as volts' = volts A^-T (so A undoes it)."""
    out = frame.copy()
    out[CHANNELS] = frame[CHANNELS].to_numpy() @ np.linalg.inv(a).T
    return out


def test_a_known_channel_mix_is_recovered_through_a_frozen_ls_model() -> None:
    # given: an LS model on one unit, and another unit whose channels are mixed and scaled
    train = make_frame(n_trials=6, seed=0)
    model = fit("ls", LSParams(), train).predictor
    a_true = np.array([[1.1, 0.05, 0.0], [0.0, 0.92, 0.04], [0.03, 0.0, 1.05]])
    seen = make_frame(n_trials=2, seed=5)
    seen[["fx", "fy", "fz"]] = model.predict(seen)  # a force the model explains exactly: A is identifiable
    unit = _distorted(seen, a_true)
    # when: fitting the unit's transform with a negligible pull towards the identity
    transform, report = fit_transform([AngleData.of(model, unit)], P.model_copy(update={"ridge": 1e-9}))
    # then: the mix is undone and the loss drops
    np.testing.assert_allclose(np.asarray(transform.matrix), a_true, atol=0.02)
    assert report["loss_after"] < 0.5 * report["loss_before"]


def test_an_axis_that_hardly_moves_does_not_steer_the_transform() -> None:
    # given: an LS model whose fy is small (a vertical insertion's lateral force), and a unit whose
    # channels read off by a gain each, recorded with a reference whose fy is only noise at that scale
    train = make_frame(n_trials=6, seed=0)
    train["fy"] *= 0.02
    model = fit("ls", LSParams(), train).predictor
    a_true = np.diag([1.1, 0.92, 1.05])
    seen = make_frame(n_trials=2, seed=5)
    seen[["fx", "fy", "fz"]] = model.predict(seen)
    seen["fy"] = 0.01 * np.random.default_rng(1).normal(size=len(seen))
    # when: fitting the unit's gains
    gains = P.model_copy(update={"ridge": 1e-9, "transform": "diagonal"})
    transform, _ = fit_transform([AngleData.of(model, _distorted(seen, a_true))], gains)
    # then: the axes that carry the force decide them, and they are undone
    np.testing.assert_allclose(np.asarray(transform.matrix), a_true, atol=0.05)


def test_a_unit_like_the_training_ones_keeps_about_the_identity() -> None:
    # given: an LS model and a unit with nothing to correct (its own training rows: LS is optimal there)
    train = make_frame(n_trials=4, seed=0)
    model = fit("ls", LSParams(), train).predictor
    # when: calibrating on the training rows themselves
    transform, report = fit_transform([AngleData.of(model, train)], P)
    # then: the transform stays close to the identity and never makes the fit worse
    np.testing.assert_allclose(np.asarray(transform.matrix), np.eye(3), atol=0.05)
    assert report["loss_after"] <= report["loss_before"]


def test_a_network_is_calibrated_through_and_never_made_worse() -> None:
    # given: a tiny FNN and a unit whose channels read 10 % high
    train = make_frame(n_trials=4, seed=0)
    model = fit("fnn", FNNParams(hidden=(8,), max_epochs=20, patience=20), train).predictor
    unit = _distorted(make_frame(n_trials=2, seed=7), np.diag([1.1, 1.1, 1.1]))
    # when: fitting its transform
    _, report = fit_transform([AngleData.of(model, unit)], P)
    # then: the loss does not rise
    assert report["loss_after"] <= report["loss_before"]


def test_the_document_says_what_was_used_missing_and_set_aside() -> None:
    # given: an LS model at 30°, calibration rows at 30° and 60°, one trial too short
    train = make_frame(n_trials=4, seed=0)
    model = fit("ls", LSParams(), train).predictor
    rows = make_frame(n_trials=2, n=120, seed=3)
    rows["unit_id"] = "u-new"
    extra = make_frame(n_trials=1, n=120, seed=4, batch_id="b2").assign(angle_deg=60.0, unit_id="u-new")
    short = make_frame(n_trials=1, n=30, seed=6, batch_id="b3").assign(unit_id="u-new")
    rows = pd.concat([rows, extra, short], ignore_index=True)
    # when: calibrating the unit for a pipeline trained at 30° and 45°
    doc = calibrate_unit("u-new", rows, {"ls": {"30": model}}, ["30", "45"], P)
    # then: 30° used, 45° missing, the 60° trial and the short trial set aside with their reasons
    assert doc["angles_used"] == ["30"] and doc["angles_missing"] == ["45"]
    reasons = {s["file"]: s["reason"] for s in doc["set_aside"]}
    assert "no shared model is trained at 60°" in reasons["b2/t00.fsr.csv"]
    assert "calibrate.min_trial_s" in reasons["b3/t00.fsr.csv"]
    assert doc["transforms"]["ls"]["fitted_through"] == ["30"]
    # and: the same inputs give the same document
    assert calibrate_unit("u-new", rows, {"ls": {"30": model}}, ["30", "45"], P) == doc


def test_the_fits_on_two_worker_processes_give_the_one_process_results(monkeypatch) -> None:
    # given: an LS and an FNN model at two angles, a unit whose channels read off, and calibration
    # rows so few that worker processes would not repay their start (the rule, turned off here)
    train = make_frame(n_trials=4, seed=0)
    models = {
        "ls": fit("ls", LSParams(), train).predictor,
        "fnn": fit("fnn", FNNParams(hidden=(8,), max_epochs=10, patience=10), train).predictor,
    }
    unit = {
        a: _distorted(make_frame(n_trials=2, seed=s), np.diag([1.1, 0.95, 1.0])) for a, s in ((0, 3), (1, 4))
    }
    data = {kind: [AngleData.of(m, unit[a]) for a in unit] for kind, m in models.items()}
    monkeypatch.setattr(calibration_fit, "WORTH_A_WORKER", 0)
    # when: fitting every kind's transform, leave-one-angle-out included, on one process and on two
    one = calibration_fit.fit_transforms(data, P, workers=1)
    two = calibration_fit.fit_transforms(data, P, workers=2)
    # then: the same transforms and reports, to the bit
    assert one.keys() == two.keys() == {"ls", "fnn"}
    for kind in one:
        assert one[kind][0].to_dict() == two[kind][0].to_dict()
        assert one[kind][1] == two[kind][1] and "held_out_loss_after" in one[kind][1]
