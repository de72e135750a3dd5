"""The live client: streaming equals the batch predictor, the stream is checked, and a client made from
the registry follows its alias between insertions. (These clients name no estimator unit: they warn
UncalibratedUnit, which tests/client/test_units.py tests.)"""

from __future__ import annotations

import logging
import shutil
from pathlib import Path

import numpy as np
import pytest

import needlecue_client as fc
from pipeline.modelling.predictor import Predictor
from tests.client.builders import CHANNELS, UNREACHABLE, Clock, Registered, cue_trials, register
from tests.projects import new_store

pytestmark = pytest.mark.filterwarnings("ignore::needlecue_client.force.UncalibratedUnit")


def test_streaming_equals_batch_predictions_of_the_trial(registered: Registered, fetched: Path) -> None:
    # given: the fetched LSTM and two unseen trials
    client = fc.ForceClient.from_dir(fetched)
    frame = cue_trials(30, 2, "b7", seed=5, n=50)
    expected = Predictor(registered.checkpoint).predict(frame)
    # when: each trial is streamed sample by sample after a reset, and the second once more without one
    streamed = []
    for _, trial in frame.groupby("trial_id", sort=True):
        client.reset()
        streamed += [
            client.step(v, t).force_n for v, t in zip(trial[CHANNELS].to_numpy(), trial["t_s"], strict=True)
        ]
    carried = [client.step(v).force_n for v in frame.loc[frame.trial_id == "t01", CHANNELS].to_numpy()]
    # then: the forces equal the batch predictor's (windows padded with the first sample), and history
    # carried over from another insertion would have changed the first window's forces
    assert client.window == 6 and client.kind == "lstm" and client.angle_deg == 30.0
    scale = np.abs(expected).max()
    np.testing.assert_allclose(np.array(streamed), expected, rtol=0, atol=1e-5 * scale)
    assert not np.allclose(carried[:5], expected[50:55], rtol=0, atol=1e-3 * scale)
    np.testing.assert_allclose(carried[6:], expected[56:], rtol=0, atol=1e-5 * scale)


def test_step_output_and_bad_samples(fetched: Path) -> None:
    # given: a client with a cue pack, its cues asked for without a unit calibration
    with pytest.warns(fc.UncalibratedUnit):
        client = fc.ForceClient.from_dir(fetched, cues_uncalibrated=True)
    # when: stepping without times, then with a wrong-length or non-finite sample
    a, b = client.step([0.6, 0.6, 0.6]), client.step(np.array([0.6, 0.7, 0.6]))
    # then: a force (3,) per frame, times on the model's grid, a cue (waiting for a rest reading at
    # first); bad samples are clear errors
    assert a.force_n.shape == (3,) and a.t_s == 0.0 and (a.cue.cue, b.cue.cue) == ("wait", "wait")
    assert b.t_s == pytest.approx(1 / client.rate_hz)
    with pytest.raises(ValueError, match=r"takes 3 volts \(fsr1, fsr2, fsr3\), got 2"):
        client.step([0.6, 0.6])
    with pytest.raises(ValueError, match="non-finite"):
        client.step([0.6, float("nan"), 0.6])


def test_a_cue_pack_of_another_format_gives_force_without_cues(
    fetched: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    # given: the fetched model, its cue pack marked as made by an older needlecue
    old = shutil.copytree(fetched, tmp_path / "old-pack")
    mlmodel = old / "MLmodel"
    mlmodel.write_text(mlmodel.read_text().replace("needlecue-cues/5", "needlecue-cues/3"))
    # when: a client loads it, cues asked for, the edited description run unverified
    with caplog.at_level(logging.WARNING, logger="needlecue_client"), pytest.warns(fc.UncalibratedUnit):
        client = fc.ForceClient.from_dir(old, cues_uncalibrated=True, unverified=True)
    # then: force every frame, no cue, and a warning that says why and what to do
    frame = client.step([0.6, 0.6, 0.6])
    assert frame.force_n.shape == (3,) and frame.cue is None
    expected = "no cues: not a needlecue-cues/5 cue pack (format 'needlecue-cues/3'): made by another"
    assert any(expected in m and "dvc repro" in m for m in caplog.messages)


def test_a_stream_the_model_was_not_trained_on_is_refused(fetched: Path) -> None:
    # given: a model trained on fsr1..3 at 30 Hz
    client = fc.ForceClient.from_dir(fetched)
    client.check_stream(CHANNELS, 30.5)  # within 5 %: fine
    # when / then: other channels, another order or another rate raise StreamMismatch saying both sides
    with pytest.raises(fc.StreamMismatch, match=r"reads \['fsr1', 'fsr2', 'fsr3'\].*missing \['fsr3'\]"):
        client.check_stream(["fsr1", "fsr2", "fsr4"], 30.0)
    with pytest.raises(fc.StreamMismatch, match="another order"):
        client.check_stream(["fsr2", "fsr1", "fsr3"], 30.0)
    with pytest.raises(fc.StreamMismatch, match="trained at 30 Hz, the stream runs at 100 Hz") as err:
        client.check_stream(CHANNELS, 100.0)
    assert isinstance(err.value, ValueError)


def test_a_folder_that_is_not_a_model_is_a_clear_error(tmp_path: Path) -> None:
    # given: an empty folder and one whose MLmodel lacks the needlecue block
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "MLmodel").write_text("flavors: {}\n")
    # when / then: each names the folder and what is missing
    with pytest.raises(FileNotFoundError, match="no MLmodel file"):
        fc.ForceClient.from_dir(tmp_path)
    with pytest.raises(ValueError, match="no needlecue-deploy/4 block"):
        fc.ForceClient.from_dir(tmp_path / "other")


# --- following the alias --------------------------------------------------------------------------

VOLTS = [0.4, 0.5, 0.6]


def predicted(checkpoint: dict, volts: list[float]) -> np.ndarray:
    """The batch predictor's force for one sample (an LS model has no history)."""
    return Predictor(checkpoint).predict_arrays(np.array([volts]))[0]


def test_reset_swaps_in_a_new_champion_once_the_poll_interval_has_passed(
    ls_models: dict[str, dict],
    tmp_path: Path,
    mlflow_store: str,
    clock: Clock,
    registry_calls: list[str | None],
    caplog: pytest.LogCaptureFixture,
) -> None:
    # given: v1 champion, a client following it (poll every 60 s) checked against a 30 Hz fsr1..3 stream
    register(mlflow_store, tmp_path, ls_models["a"])
    client = fc.ForceClient.from_registry(
        30, cache_dir=tmp_path / "cache", tracking_uri=mlflow_store, poll_s=60
    )
    client.check_stream(CHANNELS, 30.0)
    before = client.step(VOLTS).force_n
    # when: v2, another model, becomes champion and an insertion starts 59 s later
    register(mlflow_store, tmp_path, ls_models["b"])
    registry_calls.clear()
    clock.advance(59)
    client.reset()
    # then: still v1, without a single registry call
    assert client.version["version"] == "1" and registry_calls == []
    np.testing.assert_allclose(client.step(VOLTS).force_n, before)

    # when: the next insertion starts once 60 s have passed
    clock.advance(1)
    with caplog.at_level(logging.INFO, logger="needlecue_client"):
        client.reset()
    # then: v2 is loaded, said in the log, and its forces are the new model's
    assert client.version["version"] == "2" and registry_calls == [mlflow_store] * 2  # the poll, the fetch
    assert "needle-force-30: champion v1 -> v2" in caplog.messages
    after = client.step(VOLTS).force_n
    np.testing.assert_allclose(before, predicted(ls_models["a"], VOLTS), rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(after, predicted(ls_models["b"], VOLTS), rtol=1e-4, atol=1e-6)
    assert not np.allclose(after, before, rtol=1e-2)


def test_refresh_with_force_ignores_the_interval(
    ls_models: dict[str, dict], tmp_path: Path, mlflow_store: str, clock: Clock
) -> None:
    # given: a client polling every 60 s, one that never polls by itself, and one made from a folder
    register(mlflow_store, tmp_path, ls_models["a"])
    cache = tmp_path / "cache"
    polling = fc.ForceClient.from_registry(30, cache_dir=cache, tracking_uri=mlflow_store, poll_s=60)
    fixed = fc.ForceClient.from_registry(30, cache_dir=cache, tracking_uri=mlflow_store, poll_s=None)
    bare = fc.ForceClient.from_dir(polling.model_dir)
    # when: v2 becomes champion; a day passes for the client that never polls
    register(mlflow_store, tmp_path, ls_models["b"])
    clock.advance(86400)
    fixed.reset()
    # then: a plain refresh waits for the interval, a forced one loads v2 at once (and the interval
    # restarts); nothing new is no swap; a client without a registry has nothing to refresh
    assert fixed.version["version"] == "1"
    polling._follower.next_poll = clock.now + 30  # 30 s left of the polling client's interval
    assert polling.refresh() is False and polling.version["version"] == "1"
    assert polling.refresh(force=True) is True and polling.version["version"] == "2"
    assert polling.refresh(force=True) is False
    assert fixed.refresh(force=True) is True and fixed.version["version"] == "2"
    assert bare.refresh(force=True) is False and bare.version["version"] == "1"


def test_an_unreachable_registry_keeps_the_model_warns_once_and_retries_after_the_interval(
    ls_models: dict[str, dict],
    tmp_path: Path,
    clock: Clock,
    registry_calls: list[str | None],
    caplog: pytest.LogCaptureFixture,
    empty_store: Path,
) -> None:
    # given: a client following v1 of a store that then goes away (its folder moved), v2 champion there
    store = tmp_path / "store"
    uri = new_store(empty_store, store)
    register(uri, store, ls_models["a"])
    client = fc.ForceClient.from_registry(30, cache_dir=tmp_path / "cache", tracking_uri=uri, poll_s=60)
    register(uri, store, ls_models["b"])
    store.rename(tmp_path / "away")
    registry_calls.clear()
    # when: an insertion starts after the interval, another before the next one, a third after it
    with caplog.at_level(logging.DEBUG, logger="needlecue_client"):
        clock.advance(60)
        client.reset()
        client.reset()
        clock.advance(60)
        client.reset()
    # then: v1 kept, nothing raised, one warning saying so, and a poll only at each interval
    assert client.version["version"] == "1" and registry_calls == [uri, uri]
    warnings = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    warnings = [w for w in warnings if "is not calibrated" not in w]  # no unit named: said at creation
    assert len(warnings) == 1, warnings
    assert "needle-force-30@champion: cannot poll the registry" in warnings[0]
    assert "keeping needle-force-30 v1 (ls), next try in 60 s" in warnings[0]

    # when: the store is back by the next interval
    (tmp_path / "away").rename(store)
    clock.advance(60)
    client.reset()
    # then: the new champion is loaded
    assert client.version["version"] == "2"

    # when: a client started offline (from the cached copy) polls an HTTP registry that refuses connections
    offline = fc.ForceClient.from_registry(30, cache_dir=tmp_path / "cache", tracking_uri=UNREACHABLE)
    # then: no error, the copy is kept
    assert offline.refresh(force=True) is False and offline.version["version"] == "2"


def test_a_new_champion_that_does_not_fit_the_stream_is_refused(
    ls_models: dict[str, dict],
    tmp_path: Path,
    mlflow_store: str,
    clock: Clock,
    caplog: pytest.LogCaptureFixture,
) -> None:
    # given: a client of v1 checked against a fsr1..3 stream
    register(mlflow_store, tmp_path, ls_models["a"])
    client = fc.ForceClient.from_registry(
        30, cache_dir=tmp_path / "cache", tracking_uri=mlflow_store, poll_s=60
    )
    client.check_stream(CHANNELS, 30.0)
    before = client.step(VOLTS).force_n
    # when: v2, which reads fsr4 instead of fsr3, becomes champion; two insertions start an interval apart
    register(mlflow_store, tmp_path, ls_models["fsr4"])
    with caplog.at_level(logging.INFO, logger="needlecue_client"):
        clock.advance(60)
        client.reset()
        clock.advance(60)
        client.reset()
    # then: v1 kept with its forces, one error naming the channels, and v2 not tried again
    assert client.version["version"] == "1" and client.channels == tuple(CHANNELS)
    np.testing.assert_allclose(client.step(VOLTS).force_n, before)
    errors = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
    assert len(errors) == 1, errors
    assert "needle-force-30: champion v2 refused, keeping v1" in errors[0] and "fsr4" in errors[0]
