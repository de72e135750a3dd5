"""The estimator unit on the simulator: its registered calibration fetched and cached like a model,
applied when it was made with the loaded model, and otherwise a warning, the raw force and no cues."""

from __future__ import annotations

import contextlib
import json
import logging
import shutil
import warnings
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

import needlecue_client as fc
from needlecue_client.folder import ModelFolderError
from needlecue_client.replay import replay
from needlecue_runtime.features import InputTransform
from needlecue_runtime.registry import store
from needlecue_runtime.unit_calibration import FILE
from pipeline.modelling.predictor import Predictor
from tests.client.builders import (
    UNREACHABLE,
    Clock,
    Registered,
    cue_trials,
    register,
    register_unit,
    unit_document,
)

MIX = [[1.08, 0.05, 0.0], [0.0, 0.93, 0.04], [-0.03, 0.0, 1.1]]
VOLTS = [0.4, 0.5, 0.6]


@contextlib.contextmanager
def no_uncalibrated_warning() -> Iterator[None]:
    """A block in which an UncalibratedUnit warning fails the test."""
    with warnings.catch_warnings():
        warnings.simplefilter("error", fc.UncalibratedUnit)
        yield


def test_fetch_unit_caches_the_calibration_and_falls_back_to_it_offline(
    registered: Registered, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    # given: a unit's calibration registered, and an empty cache
    doc = unit_document("est-f1", {30: registered.checkpoint}, MIX)
    version = register_unit(registered.uri, doc)
    cache = tmp_path / "cache"
    # when: fetching it
    folder = fc.fetch_unit("est-f1", cache_dir=cache, tracking_uri=registered.uri)
    # then: calibration.json (the document) and a version.json saying what it is
    assert folder == cache / "needle-unit-est-f1" / "current"
    assert json.loads((folder / FILE).read_text()) == doc
    info = json.loads((folder / fc.VERSION_FILE).read_text())
    assert (info["name"], info["version"], info["alias"], info["unit_id"]) == (
        "needle-unit-est-f1",
        str(version),
        "current",
        "est-f1",
    )
    assert info["source"].endswith("/calibration") and info["calibration_sha256"]
    # when: the registry is unreachable
    with caplog.at_level(logging.WARNING, logger="needlecue_client"):
        offline = fc.fetch_unit("est-f1", cache_dir=cache, tracking_uri=UNREACHABLE)
    # then: the cached copy, with a warning
    assert offline == folder and "offline" in caplog.text and "needle-unit-est-f1@current" in caplog.text
    # and: a unit never registered is ModelNotFound with the fix; offline without a copy, unreachable
    with pytest.raises(fc.ModelNotFound, match=r"needle-unit-est-nobody.*needlecue calibrate BATCH_DIR"):
        fc.fetch_unit("est-nobody", cache_dir=cache, tracking_uri=registered.uri)
    with pytest.raises(fc.RegistryUnreachable, match="no local copy"):
        fc.fetch_unit("est-nobody", cache_dir=cache, tracking_uri=UNREACHABLE)


def test_a_calibrated_client_streams_what_the_predictor_gives_through_the_transform(
    registered: Registered, tmp_path: Path
) -> None:
    # given: the 30° LSTM champion and a unit calibrated with it (a channel mix)
    doc = unit_document("est-c1", {30: registered.checkpoint}, MIX)
    register_unit(registered.uri, doc)
    trial = cue_trials(30, 1, "unit-c1", seed=9, n=80)
    # when: a client of that unit replays a trial
    with no_uncalibrated_warning():
        client = fc.ForceClient.from_registry(
            30, unit_id="est-c1", cache_dir=tmp_path / "cache", tracking_uri=registered.uri
        )
        out = replay(trial, client)
    # then: calibrated, the forces are the batch predictor's through the unit's transform, and it cues
    assert client.calibrated and client.uncalibrated_reason is None and client.unit_id == "est-c1"
    assert client.calibration["name"] == "needle-unit-est-c1" and client.calibration["version"] == "1"
    expected = Predictor(registered.checkpoint).predict(
        trial, InputTransform.from_dict(doc["transforms"]["lstm"])
    )
    scale = np.abs(expected).max()
    np.testing.assert_allclose(out[["fx", "fy", "fz"]].to_numpy(), expected, rtol=0, atol=1e-5 * scale)
    assert not np.allclose(expected, Predictor(registered.checkpoint).predict(trial), atol=1e-3 * scale)
    assert client.has_cues and out["cue"].notna().all()


def test_an_unknown_unit_warns_and_gives_force_without_cues(registered: Registered, tmp_path: Path) -> None:
    # given: a unit that was never calibrated
    trial = cue_trials(30, 1, "unit-x", seed=2)
    # when: a client is made for it
    with pytest.warns(fc.UncalibratedUnit, match=r"'est-nobody' is not calibrated.*needlecue calibrate") as w:
        client = fc.ForceClient.from_registry(
            30, unit_id="est-nobody", cache_dir=tmp_path / "cache", tracking_uri=registered.uri
        )
    out = replay(trial, client)
    # then: one warning saying why; the model's raw force; no cue on any frame
    assert len(w) == 1 and "no registered calibration" in str(w[0].message)
    assert not client.calibrated and client.calibration is None and not client.has_cues
    assert "needle-unit-est-nobody@current" in client.uncalibrated_reason
    assert out["cue"].isna().all()
    expected = Predictor(registered.checkpoint).predict(trial)
    np.testing.assert_allclose(
        out[["fx", "fy", "fz"]].to_numpy(), expected, rtol=0, atol=1e-5 * np.abs(expected).max()
    )
    # and: no unit named at all, the same
    with pytest.warns(fc.UncalibratedUnit, match="no estimator unit named"):
        nameless = fc.ForceClient.from_registry(30, cache_dir=tmp_path / "cache", tracking_uri=registered.uri)
    assert nameless.step(VOLTS).cue is None and nameless.unit_id is None


def test_cues_uncalibrated_gives_the_cues_all_the_same(registered: Registered, tmp_path: Path) -> None:
    # given: an uncalibrated unit, asking for cues anyway
    with pytest.warns(fc.UncalibratedUnit, match="and its cues anyway"):
        client = fc.ForceClient.from_registry(
            30,
            unit_id="est-nobody",
            cues_uncalibrated=True,
            cache_dir=tmp_path / "cache",
            tracking_uri=registered.uri,
        )
    # when: replaying a trial
    out = replay(cue_trials(30, 1, "unit-x", seed=2), client)
    # then: cues as before calibrations existed
    assert not client.calibrated and client.has_cues
    assert out["cue"].iloc[0] == "wait" and out["cue"].notna().all()


def test_a_calibration_made_with_other_models_or_given_as_a_file(
    registered: Registered, fetched: Path, tmp_path: Path
) -> None:
    # given: the unit's document made with another LSTM at 30°, one with none at 30°, and a good one
    stale = unit_document("est-d1", {30: registered.checkpoint}, MIX)
    stale["transforms"]["lstm"]["models"]["30"] = "0" * 64
    elsewhere = unit_document("est-d1", {30: registered.checkpoint}, MIX)
    elsewhere["transforms"]["lstm"]["models"] = {"45": "0" * 64}
    good = tmp_path / "est-d1.json"
    good.write_text(json.dumps(unit_document("est-d1", {30: registered.checkpoint}, MIX)))
    # when / then: the first two leave the client uncalibrated, each saying why
    with pytest.warns(fc.UncalibratedUnit, match="made with another lstm model at 30°"):
        assert not fc.ForceClient.from_dir(fetched, calibration=stale).calibrated
    with pytest.warns(fc.UncalibratedUnit, match="not made with a lstm model at 30°"):
        assert not fc.ForceClient.from_dir(fetched, calibration=elsewhere).calibrated
    # and: a calibration.json applies, its unit is the client's, another unit_id is refused
    with no_uncalibrated_warning():
        client = fc.ForceClient.from_dir(fetched, calibration=good)
    assert client.calibrated and client.unit_id == "est-d1" and client.calibration["path"] == str(good)
    with pytest.raises(ValueError, match="of unit 'est-d1', not 'est-d2'"):
        fc.ForceClient.from_dir(fetched, calibration=good, unit_id="est-d2")
    # and: a model logged before needlecue-deploy/4 (its graph reads the model's inputs, not what the
    # estimator sends) is not run at all, even unverified: it says to register it again
    old = tmp_path / "deploy3"
    shutil.copytree(fetched, old)
    (old / "MLmodel").write_text(
        (old / "MLmodel").read_text().replace("needlecue-deploy/4", "needlecue-deploy/3")
    )
    with pytest.raises(ModelFolderError, match=r"a needlecue-deploy/3 model, .* register it again"):
        fc.ForceClient.from_dir(old, calibration=good, unverified=True)


def test_a_new_champion_is_checked_against_the_calibration_and_a_new_calibration_is_picked_up(
    ls_models: dict[str, dict], tmp_path: Path, mlflow_store: str, clock: Clock
) -> None:
    # given: v1 champion, the unit calibrated with it, and a client of that unit polling every 60 s
    register(mlflow_store, tmp_path, ls_models["a"])
    register_unit(mlflow_store, unit_document("est-s1", {30: ls_models["a"]}, MIX))
    client = fc.ForceClient.from_registry(
        30, unit_id="est-s1", cache_dir=tmp_path / "cache", tracking_uri=mlflow_store, poll_s=60
    )
    assert client.calibrated
    # when: v2, which the calibration was not made with, becomes champion and the next insertion starts
    register(mlflow_store, tmp_path, ls_models["b"])
    clock.advance(60)
    with pytest.warns(fc.UncalibratedUnit, match="made with another ls model at 30°"):
        client.reset()
    # then: v2 runs, uncalibrated: its raw force, no transform
    assert client.version["version"] == "2" and not client.calibrated
    raw = Predictor(ls_models["b"]).predict_arrays(np.array([VOLTS]))[0]
    np.testing.assert_allclose(client.step(VOLTS).force_n, raw, rtol=1e-4, atol=1e-6)
    # when: the unit is calibrated again, with v2 (`needlecue calibrate`), and the client refreshes
    doc = unit_document("est-s1", {30: ls_models["b"]}, MIX)
    assert register_unit(mlflow_store, doc) == 2
    with no_uncalibrated_warning():
        assert client.refresh(force=True) is True
    # then: calibrated with the new version, and its force goes through the transform
    assert client.calibrated and client.calibration["version"] == "2"
    transform = InputTransform.from_dict(doc["transforms"]["ls"])
    calibrated = Predictor(ls_models["b"]).predict_arrays(np.array([VOLTS]), transform=transform)[0]
    client.reset()
    np.testing.assert_allclose(client.step(VOLTS).force_n, calibrated, rtol=1e-4, atol=1e-6)
    assert client.refresh(force=True) is False  # nothing new
    assert store.UNIT_ALIAS == fc.UNIT_ALIAS == "current"
