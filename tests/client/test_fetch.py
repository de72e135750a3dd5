"""Fetching from the registry into a cache that survives going offline, and follows the alias."""

from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path

import pytest

import needlecue_client as fc
from needlecue_client.cache import poll_alias
from needlecue_client.folder import read_metadata
from needlecue_runtime.registry import store
from needlecue_runtime.vocab import description_sha256
from pipeline.modelling.checkpoint import checkpoint_sha256
from pipeline.modelling.export import to_onnx
from pipeline.modelling.fit import fit
from tests.client.builders import TINY, UNREACHABLE, Registered, cue_trials, register

pytestmark = pytest.mark.filterwarnings("ignore::needlecue_client.force.UncalibratedUnit")


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
    assert version["run_id"] and version["checkpoint_sha256"] == checkpoint_sha256(registered.checkpoint)
    meta = read_metadata(folder)  # the graph carries its description's hash
    assert (folder / "model.onnx").read_bytes() == to_onnx(registered.checkpoint, description_sha256(meta))
    assert sorted(p.name for p in folder.parent.iterdir()) == ["champion"]

    # when: fetching again with the same version registered (a download would fail loudly)
    def no_download(**_kwargs):
        raise AssertionError("downloaded the version already cached")

    monkeypatch.setattr("mlflow.artifacts.download_artifacts", no_download)
    # then: the cached copy is reused
    assert fc.fetch(30, cache_dir=cache, tracking_uri=registered.uri) == folder

    # when: the registry is unreachable, over HTTP and as a sqlite file in a missing folder
    with caplog.at_level(logging.WARNING, logger="needlecue_client"):
        offline = fc.fetch(30, cache_dir=cache, tracking_uri=UNREACHABLE)
        gone = fc.fetch(30, cache_dir=cache, tracking_uri=f"sqlite:///{tmp_path / 'nope' / 'mlflow.db'}")
    # then: the local copy is used, with a warning saying so
    assert offline == gone == folder
    warned = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warned) == 2 and all(m.startswith("offline: ") and str(folder) in m for m in warned)


def test_fetch_takes_only_what_a_simulator_runs_and_refuses_a_version_without_it(
    mlflow_store: str, tmp_path: Path
) -> None:
    # given: a champion of this test's own store, fetched into an empty cache
    register(mlflow_store, tmp_path, fit("ls", TINY["ls"], cue_trials(30, 3)).checkpoint)
    folder = fc.fetch(30, cache_dir=tmp_path / "cache", tracking_uri=mlflow_store)
    # then: the folder holds the model's description, its ONNX and what the cache knows of it, not the
    # logged model's environment files and examples (each file costs requests through a server)
    assert sorted(p.name for p in folder.iterdir()) == ["MLmodel", "model.onnx", "version.json"]
    # when: the registered version has lost its ONNX (a broken upload, say)
    from mlflow import MlflowClient

    location = MlflowClient(mlflow_store).get_model_version_download_uri("needle-force-30", "1")
    Path(location.removeprefix("file://"), "model.onnx").unlink()
    # then: fetching it into a new cache is an error naming the file, not "offline"
    with pytest.raises(ValueError, match=r"needle-force-30 version 1 .* has no model\.onnx"):
        fc.fetch(30, cache_dir=tmp_path / "other", tracking_uri=mlflow_store)


def test_fetch_offline_without_a_copy_names_the_model_and_the_cache(tmp_path: Path) -> None:
    # given: an unreachable registry and an empty cache
    cache = tmp_path / "cache"
    # when / then: a RegistryUnreachable naming the model URI, the store and where a copy would be
    with pytest.raises(store.RegistryUnreachable) as err:
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
    register(mlflow_store, tmp_path, fit("fnn", TINY["fnn"], train).checkpoint)
    first = fc.ForceClient.from_registry(30, cache_dir=cache, tracking_uri=mlflow_store)
    # when: fetching version 1 of another store (the package's LSTM), then version 2 (an LS model) made
    # champion here
    other = fc.ForceClient.from_registry(30, cache_dir=cache, tracking_uri=registered.uri)
    register(mlflow_store, tmp_path, fit("ls", TINY["ls"], train).checkpoint)
    second = fc.ForceClient.from_registry(30, cache_dir=cache, tracking_uri=mlflow_store)
    # then: each fetch swaps in the model it resolved (another store's "v1" is another model), whole,
    # with no temp folders left beside it; without a cue pack the client gives forces and no cues
    assert (first.kind, first.version["version"]) == ("fnn", "1")
    assert (other.kind, other.version["version"]) == ("lstm", "1")
    assert (second.kind, second.version["version"]) == ("ls", "2")
    assert sorted(p.name for p in (cache / "needle-force-30").iterdir()) == ["champion"]
    assert not second.has_cues and second.step([0.3, 0.3, 0.3]).cue is None


def test_a_default_store_that_is_not_there_is_unreachable_not_created(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # given: the client run outside the project, where no mlflow.db exists, with no local copy
    store_uri = f"sqlite:///{tmp_path / 'elsewhere' / 'mlflow.db'}"
    (tmp_path / "elsewhere").mkdir()
    # when / then: it says the registry cannot be reached, and creates no empty store there
    with pytest.raises(store.RegistryUnreachable, match="no such database"):
        fc.fetch(30, cache_dir=tmp_path / "cache", tracking_uri=store_uri)
    assert not (tmp_path / "elsewhere" / "mlflow.db").exists()


def _cached_copy(registered: Registered, tmp_path: Path) -> tuple[Path, Path]:
    """(cache, its 30° champion folder) fetched from the registry."""
    cache = tmp_path / "cache"
    return cache, fc.fetch(30, cache_dir=cache, tracking_uri=registered.uri)


@pytest.mark.parametrize(
    ("tamper", "why"),
    [
        (
            lambda f: f.joinpath("model.onnx").write_bytes(b"\0" + f.joinpath("model.onnx").read_bytes()),
            "model.onnx is not the file fetched",
        ),
        (lambda f: f.joinpath("MLmodel").write_text("- just\n- a list\n"), "MLmodel: not an MLmodel file"),
        (
            lambda f: f.joinpath("MLmodel").write_text(
                f.joinpath("MLmodel").read_text().replace("angle_deg: 30.0", "angle_deg: 45.0")
            ),
            r"needlecue\.angle_deg differs from the graph's own",
        ),
        (
            lambda f: f.joinpath("version.json").write_text(
                f.joinpath("version.json").read_text().replace('"1"', '""')
            ),
            "names no version",
        ),
    ],
    ids=["onnx changed", "MLmodel not a mapping", "another angle's MLmodel", "no version"],
)
def test_offline_a_copy_that_fails_its_check_is_refused(
    registered: Registered, tmp_path: Path, tamper, why: str
) -> None:
    # given: a fetched champion, then changed in the cache
    cache, folder = _cached_copy(registered, tmp_path)
    tamper(folder)
    # when: the registry is unreachable / then: the copy is refused, saying where and why
    with pytest.raises(fc.CachedCopyRefused, match=why) as err:
        fc.fetch(30, cache_dir=cache, tracking_uri=UNREACHABLE)
    assert str(folder) in str(err.value) and "models:/needle-force-30@champion" in str(err.value)


def test_offline_another_angle_s_copy_in_the_folder_is_refused(
    registered: Registered, tmp_path: Path
) -> None:
    # given: the 30° champion's whole folder copied where the 45° champion's belongs
    cache, folder = _cached_copy(registered, tmp_path)
    shutil.copytree(folder, cache / "needle-force-45" / "champion")
    # when / then: offline, the 45° client does not run the 30° model
    with pytest.raises(fc.CachedCopyRefused, match=r"version\.json is of 'needle-force-30'"):
        fc.fetch(45, cache_dir=cache, tracking_uri=UNREACHABLE)


def test_a_malformed_mlmodel_is_a_clear_error(registered: Registered, tmp_path: Path) -> None:
    # given: a model folder whose MLmodel is not YAML at all
    _, folder = _cached_copy(registered, tmp_path)
    broken = tmp_path / "broken"
    shutil.copytree(folder, broken)
    (broken / "MLmodel").write_bytes(b"\xff\xfe{{{not yaml")
    # when / then: a ValueError naming the file, not a traceback from deep in a parser
    with pytest.raises(ValueError, match="MLmodel: not valid YAML"):
        fc.ForceClient.from_dir(broken)


@pytest.mark.parametrize(
    "not_mlflow",
    [(500, b"<html>oops</html>"), (503, b"<html>down</html>")],
    ids=["500", "503"],
    indirect=True,
)
def test_a_poll_that_meets_a_server_error_is_unreachable_after_one_request(not_mlflow) -> None:
    # given: a server answering every request with a server error (a proxy before a stopped MLflow, say)
    uri, seen = not_mlflow
    # when: a simulator's client polls where the champion points
    with pytest.raises(store.RegistryUnreachable, match=f"registry at {uri}"):
        poll_alias("needle-force-30", store.CHAMPION, uri)
    # then: it asked once: no retry and no checks after it, on a server already in trouble
    assert seen == ["GET /api/2.0/mlflow/registered-models/alias"]


@pytest.mark.parametrize(
    "not_mlflow",
    [(404, b'{"error_code": "RESOURCE_DOES_NOT_EXIST", "message": "Not found"}')],
    ids=["404 JSON no such thing"],
    indirect=True,
)
def test_a_poll_answered_4xx_takes_the_checks_that_say_what_is_wrong(not_mlflow) -> None:
    # given: a web server that answers every request "no such thing", as no MLflow server does
    uri, seen = not_mlflow
    # when: a client polls it, then: it is named as not MLflow, found by the store's checks after the poll
    with pytest.raises(store.NotMlflow, match="answers, but not as an MLflow tracking server"):
        poll_alias("needle-force-30", store.CHAMPION, uri)
    assert seen[0] == "GET /api/2.0/mlflow/registered-models/alias" and len(seen) > 1
