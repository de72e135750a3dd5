"""The simulator's client: fetch from the registry into a cache that survives going offline, check the
stream, and stream a trial sample by sample to the same forces the batch predictor gives."""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from pipeline import client as fc
from pipeline import export, registry
from pipeline import models as m
from pipeline.cli import app
from tests.test_export import CHANNELS, TINY

UNREACHABLE = "http://127.0.0.1:9"  # the discard port: connection refused at once


@dataclass(frozen=True)
class Registered:
    uri: str  # the module's own MLflow store
    checkpoint: dict  # the LSTM registered there as needle-force-30@champion, version 1, with a cue pack


def cue_trials(
    angle: float, n_trials: int = 2, batch: str = "b1", seed: int = 0, n: int = 90
) -> pd.DataFrame:
    """Processed-split rows at one insertion angle: 1 s at rest, then loading. The rest reading and the
    direction the volts move in both depend on the angle, as on the real estimator, so the cue tracker's
    angle estimate can tell the angles apart."""
    rng = np.random.default_rng(seed + int(angle))
    direction = np.array([1.0 + angle / 30, 1.0, 1.0 - angle / 60])
    rest = 0.3 + 0.004 * angle * np.array([1.0, -0.5, 0.2])
    t = np.arange(n) / 30.0
    load = np.clip(t - 1.0, 0, None) ** 1.5
    parts = []
    for k in range(n_trials):
        v = rest * np.exp(0.3 * load[:, None] * direction) + 0.001 * rng.normal(size=(n, 3))
        a = np.radians(angle)
        parts.append(
            pd.DataFrame(
                {
                    "batch_id": batch,
                    "trial_id": f"t{k:02d}",
                    "angle_deg": float(angle),
                    "tissue_point": "p1",
                    "t_s": t,
                    "phase": np.where(t < 1.0, "rest", "insertion"),
                    **{c: v[:, i] for i, c in enumerate(CHANNELS)},
                    "fx": 0.2 * load * np.sin(a) + 0.05 * v[:, 0],
                    "fy": 0.1 * load,
                    "fz": -0.5 * load * np.cos(a),
                }
            )
        )
    return pd.concat(parts, ignore_index=True)


def register(uri: str, root: Path, checkpoint: dict, pack: dict | None = None, angle: float = 30.0) -> str:
    """Log `checkpoint` as ONNX in store `uri` (artifacts under `root`), register it, make it champion."""
    import mlflow

    client = registry.connect(uri)
    name = registry.model_name(angle)
    exp = mlflow.get_experiment_by_name(registry.EXPERIMENT)
    exp_id = (
        exp.experiment_id
        if exp
        else mlflow.create_experiment(registry.EXPERIMENT, artifact_location=(root / "artifacts").as_uri())
    )
    with mlflow.start_run(experiment_id=exp_id):
        info = export.log_onnx_model(checkpoint, pack)
    version = mlflow.register_model(info.model_uri, name).version
    client.set_registered_model_alias(name, registry.CHAMPION, version)
    return str(version)


@pytest.fixture(scope="module")
def registered(tmp_path_factory: pytest.TempPathFactory) -> Registered:
    """A tiny 30° LSTM and its cue pack (from four angles' training trials), registered once for the
    whole module in a store of its own."""
    from pipeline import cues

    root = tmp_path_factory.mktemp("registry")
    uri = f"sqlite:///{root / 'mlflow.db'}"
    train = {a: cue_trials(a, 3, "b1") for a in (0, 15, 30, 45)}
    train = {a: pd.concat([f, cue_trials(a, 3, "b2", seed=1)], ignore_index=True) for a, f in train.items()}
    checkpoint = m.fit("lstm", TINY["lstm"], train[30]).checkpoint
    pack = cues.build_cue_pack(train, 30, cues.CuesParams(), m.Predictor(checkpoint))
    register(uri, root, checkpoint, pack)
    return Registered(uri, checkpoint)


@pytest.fixture(scope="module")
def fetched(registered: Registered, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The registered model fetched once into a module cache (read-only for the tests)."""
    return fc.fetch(30, cache_dir=tmp_path_factory.mktemp("cache"), tracking_uri=registered.uri)


def test_fetch_downloads_once_and_falls_back_to_the_copy_when_offline(
    registered: Registered, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    # given: an empty cache
    cache = tmp_path / "cache"
    # when: fetching the champion
    folder = fc.fetch(30, cache_dir=cache, tracking_uri=registered.uri)
    # then: the model folder and a version.json saying what it is, and no temp folders left over
    assert folder == cache / "needle-force-30" / "champion"
    version = json.loads((folder / "version.json").read_text())
    assert (version["name"], version["version"], version["alias"]) == ("needle-force-30", "1", "champion")
    assert version["run_id"] and version["checkpoint_sha256"] == export.checkpoint_sha256(
        registered.checkpoint
    )
    assert (folder / "model.onnx").read_bytes() == export.to_onnx(registered.checkpoint)
    assert sorted(p.name for p in folder.parent.iterdir()) == ["champion"]

    # when: fetching again with the same version registered (a download would fail loudly)
    def no_download(**_kwargs):
        raise AssertionError("downloaded the version already cached")

    monkeypatch.setattr("mlflow.artifacts.download_artifacts", no_download)
    # then: the cached copy is reused
    assert fc.fetch(30, cache_dir=cache, tracking_uri=registered.uri) == folder

    # when: the registry is unreachable, over HTTP and as a sqlite file in a missing folder
    with caplog.at_level(logging.WARNING, logger="pipeline.client"):
        offline = fc.fetch(30, cache_dir=cache, tracking_uri=UNREACHABLE)
        gone = fc.fetch(30, cache_dir=cache, tracking_uri=f"sqlite:///{tmp_path / 'nope' / 'mlflow.db'}")
    # then: the local copy is used, with a warning saying so
    assert offline == gone == folder
    assert caplog.text.count("offline") == 2 and str(folder) in caplog.text


def test_fetch_offline_without_a_copy_names_the_model_and_the_cache(tmp_path: Path) -> None:
    # given: an unreachable registry and an empty cache
    cache = tmp_path / "cache"
    # when / then: a RegistryUnreachable naming the model URI, the store and where a copy would be
    with pytest.raises(registry.RegistryUnreachable) as err:
        fc.fetch(45, cache_dir=cache, tracking_uri=UNREACHABLE)
    message = str(err.value)
    assert "models:/needle-force-45@champion" in message and UNREACHABLE in message
    assert str(cache / "needle-force-45" / "champion") in message


def test_fetch_of_an_unknown_alias_or_angle_is_a_clear_error(registered: Registered, tmp_path: Path) -> None:
    # given: a registry holding needle-force-30@champion only
    # when / then: another alias or angle is ModelNotFound, naming it (no silent fallback)
    with pytest.raises(fc.ModelNotFound, match="'needle-force-30' with the alias 'challenger'"):
        fc.fetch(30, "challenger", cache_dir=tmp_path, tracking_uri=registered.uri)
    with pytest.raises(fc.ModelNotFound, match="needle-force-60"):
        fc.fetch(60, cache_dir=tmp_path, tracking_uri=registered.uri)


def test_fetch_replaces_the_copy_when_the_alias_moves(
    registered: Registered, tmp_path: Path, mlflow_store: str
) -> None:
    # given: version 1 (an FNN) of this test's store fetched
    cache = tmp_path / "cache"
    train = cue_trials(30, 3)
    register(mlflow_store, tmp_path, m.fit("fnn", TINY["fnn"], train).checkpoint)
    first = fc.ForceClient.from_registry(30, cache_dir=cache, tracking_uri=mlflow_store)
    # when: fetching version 1 of another store (the module's LSTM), then version 2 (an LS model) made
    # champion here
    other = fc.ForceClient.from_registry(30, cache_dir=cache, tracking_uri=registered.uri)
    register(mlflow_store, tmp_path, m.fit("ls", TINY["ls"], train).checkpoint)
    second = fc.ForceClient.from_registry(30, cache_dir=cache, tracking_uri=mlflow_store)
    # then: each fetch swaps in the model it resolved (another store's "v1" is another model), whole,
    # with no temp folders left beside it; without a cue pack the client gives forces and no cues
    assert (first.kind, first.version["version"]) == ("fnn", "1")
    assert (other.kind, other.version["version"]) == ("lstm", "1")
    assert (second.kind, second.version["version"]) == ("ls", "2")
    assert sorted(p.name for p in (cache / "needle-force-30").iterdir()) == ["champion"]
    assert not second.has_cues and second.step([0.3, 0.3, 0.3]).cue is None


def test_streaming_equals_batch_predictions_of_the_trial(registered: Registered, fetched: Path) -> None:
    # given: the fetched LSTM and two unseen trials
    client = fc.ForceClient.from_dir(fetched)
    frame = cue_trials(30, 2, "b7", seed=5, n=50)
    expected = m.Predictor(registered.checkpoint).predict(frame)
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
    # given: a client with a cue pack
    client = fc.ForceClient.from_dir(fetched)
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
    with pytest.raises(ValueError, match="no needlecue-deploy/1 block"):
        fc.ForceClient.from_dir(tmp_path / "other")


def test_replay_command_prints_the_summary_and_writes_the_plot(
    registered: Registered, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # given: a processed parquet of two trials at 45°, the registry and an empty model cache
    data = tmp_path / "external.parquet"
    cue_trials(45, 2, "held", seed=3).to_parquet(data)
    monkeypatch.setenv("MLFLOW_TRACKING_URI", registered.uri)
    monkeypatch.setenv(fc.CACHE_ENV, str(tmp_path / "cache"))
    runner = CliRunner()
    # when: replaying the second trial against the 30° champion
    png = tmp_path / "plot.png"
    result = runner.invoke(
        app, ["replay", str(data), "--angle", "30", "--trial", "held/t01", "--out", str(png)]
    )
    # then: exit 0, the model named, a timeline that waits for the rest reading, then says to correct
    # the angle (45° is 15° off the preset), the RMSE per axis and a PNG
    assert result.exit_code == 0, result.output
    lines = result.output.splitlines()
    assert lines[0] == "held/t01: 90 samples through needle-force-30 v1 (lstm), preset angle 30°"
    timeline = [line.split()[2] for line in lines[1:-2]]
    assert timeline == ["wait", "correct"], result.output
    assert "angle    45°" in lines[-3]
    assert "RMSE vs reference: fx" in result.output and f"wrote {png}" in result.output
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

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


def test_replay_returns_one_row_per_sample_in_time_order(fetched: Path) -> None:
    # given: one trial at the preset angle, its rows shuffled
    client = fc.ForceClient.from_dir(fetched)
    trial = cue_trials(30, 1, seed=4, n=60)
    shuffled = trial.sample(frac=1.0, random_state=0)
    # when: replaying it
    out = fc.replay(shuffled, client)
    # then: t_s ascending, predictions beside the reference, the RMSE per axis, and the cue per sample,
    # ending on "continue" at the estimated preset angle
    assert list(out.columns) == [
        "t_s",
        "fx",
        "fy",
        "fz",
        "fx_ref",
        "fy_ref",
        "fz_ref",
        "cue",
        "angle_est_deg",
        "reason",
    ]
    assert out["t_s"].is_monotonic_increasing and len(out) == 60
    np.testing.assert_allclose(out["fx_ref"], trial["fx"])
    assert set(fc.rmse(out)) == {"fx", "fy", "fz"}
    assert out["cue"].iloc[0] == "wait" and (out["cue"].iloc[-1], out["angle_est_deg"].iloc[-1]) == (
        "continue",
        30,
    )
    assert list(fc.cue_changes(out)["cue"]) == ["wait", "continue"]
    with pytest.raises(ValueError, match="one trial at a time"):
        fc.replay(cue_trials(30, 2, n=10), client)
    with pytest.raises(fc.StreamMismatch, match="lacks column"):
        fc.replay(trial.drop(columns="fsr2"), client)


def test_a_cue_pack_without_an_angle_estimator_cues_by_the_profile(tmp_path: Path, mlflow_store: str) -> None:
    # given: an LS model registered with the pack of a project trained at one angle only (no angle
    # estimator can be fitted: the pack has none, and says why)
    from pipeline import cues

    train = pd.concat([cue_trials(30, 3, "b1"), cue_trials(30, 3, "b2", seed=1)], ignore_index=True)
    checkpoint = m.fit("ls", TINY["ls"], train).checkpoint
    pack = cues.build_cue_pack({30: train}, 30, cues.CuesParams(), m.Predictor(checkpoint))
    assert pack["angle_estimator"] is None and "angle_estimator" in pack["unavailable"]
    register(mlflow_store, tmp_path, checkpoint, pack)
    # when: the client fetches it and replays a trial
    client = fc.ForceClient.from_registry(30, cache_dir=tmp_path / "cache", tracking_uri=mlflow_store)
    out = fc.replay(cue_trials(30, 1, "held", seed=7), client)
    # then: it has cues, from the paper's profile method, each saying that the angle estimate is unavailable
    assert client.has_cues
    assert out["angle_est_deg"].isna().all() and out["cue"].notna().all()
    assert out["reason"].str.startswith("angle estimate unavailable").all()
    assert out["cue"].iloc[-1] in ("continue", "correct", "stop")


# --- following the alias --------------------------------------------------------------------------


class Clock:
    """The client's poll clock (`fc._monotonic`), moved by hand instead of sleeping."""

    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now

    def advance(self, seconds: float) -> None:
        self.now += seconds


@pytest.fixture
def clock(monkeypatch: pytest.MonkeyPatch) -> Clock:
    c = Clock()
    monkeypatch.setattr(fc, "_monotonic", c)
    return c


@pytest.fixture
def registry_calls(monkeypatch: pytest.MonkeyPatch) -> list[str | None]:
    """The store of every registry.connect (a poll, or a fetch), in order."""
    calls: list[str | None] = []
    real = registry.connect

    def counting(uri: str | None = None, **kwargs: bool) -> object:
        calls.append(uri)
        return real(uri, **kwargs)

    monkeypatch.setattr(registry, "connect", counting)
    return calls


@pytest.fixture(scope="module")
def ls_models() -> dict[str, dict]:
    """Tiny 30° LS checkpoints: `a`, `b` (trained on doubled forces: other predictions) and `fsr4` (reads
    fsr1, fsr2, fsr4 instead of fsr3)."""
    train = cue_trials(30, 2)
    doubled = train.assign(**{c: 2 * train[c] for c in m.TARGETS})
    return {
        "a": m.fit("ls", TINY["ls"], train).checkpoint,
        "b": m.fit("ls", TINY["ls"], doubled).checkpoint,
        "fsr4": m.fit("ls", TINY["ls"], train.rename(columns={"fsr3": "fsr4"})).checkpoint,
    }


VOLTS = [0.4, 0.5, 0.6]


def predicted(checkpoint: dict, volts: list[float]) -> np.ndarray:
    """The batch predictor's force for one sample (an LS model has no history)."""
    return m.Predictor(checkpoint).predict_arrays(np.array([volts]))[0]


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
    with caplog.at_level(logging.INFO, logger="pipeline.client"):
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
    polling._follow.next_poll = clock.now + 30  # 30 s left of the polling client's interval
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
) -> None:
    # given: a client following v1 of a store that then goes away (its folder moved), v2 champion there
    store = tmp_path / "store"
    store.mkdir()
    uri = f"sqlite:///{store / 'mlflow.db'}"
    register(uri, store, ls_models["a"])
    client = fc.ForceClient.from_registry(30, cache_dir=tmp_path / "cache", tracking_uri=uri, poll_s=60)
    register(uri, store, ls_models["b"])
    store.rename(tmp_path / "away")
    registry_calls.clear()
    # when: an insertion starts after the interval, another before the next one, a third after it
    with caplog.at_level(logging.DEBUG, logger="pipeline.client"):
        clock.advance(60)
        client.reset()
        client.reset()
        clock.advance(60)
        client.reset()
    # then: v1 kept, nothing raised, one warning saying so, and a poll only at each interval
    assert client.version["version"] == "1" and registry_calls == [uri, uri]
    warnings = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
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
    with caplog.at_level(logging.INFO, logger="pipeline.client"):
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


def test_a_default_store_that_is_not_there_is_unreachable_not_created(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # given: the client run outside the project, where no mlflow.db exists, with no local copy
    store = f"sqlite:///{tmp_path / 'elsewhere' / 'mlflow.db'}"
    (tmp_path / "elsewhere").mkdir()
    # when / then: it says the registry cannot be reached, and creates no empty store there
    with pytest.raises(registry.RegistryUnreachable, match="no such database"):
        fc.fetch(30, cache_dir=tmp_path / "cache", tracking_uri=store)
    assert not (tmp_path / "elsewhere" / "mlflow.db").exists()
