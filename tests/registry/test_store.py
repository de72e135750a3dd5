"""The registry check before anything changes: a server that is not MLflow and a read-only store are
told apart from a working store, and from each other."""

from __future__ import annotations

import os
import re
import sqlite3
from contextlib import closing
from pathlib import Path

import pytest
from mlflow import MlflowClient
from typer.testing import CliRunner

from needlecue_runtime.registry import mlflow_env, store
from needlecue_runtime.registry.store import CHAMPION, TAG, model_name
from needlecue_runtime.vocab import DEPLOY_FORMAT
from pipeline.cli import app
from pipeline.registry import versions

PAGE = b"<html><body>Welcome</body></html>"
NO_SUCH = b'{"error_code": "RESOURCE_DOES_NOT_EXIST", "message": "Not found"}'


@pytest.mark.parametrize(
    "not_mlflow",
    [(200, b"{}"), (200, PAGE), (404, PAGE), (404, NO_SUCH)],
    ids=["200 {}", "200 page", "404 page", "404 JSON no such thing"],
    indirect=True,
)
def test_a_server_that_is_not_mlflow_is_named_so_before_any_write(not_mlflow, monkeypatch) -> None:
    # given: a web server answering every request with the same status and body, as the tracking URI
    uri, seen = not_mlflow
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    # when: a writer connects (rollback, as `needlecue rollback 30` does)
    result = CliRunner().invoke(app, ["rollback", "30", "--to", "1"])
    # then: refused (exit 1) as not MLflow, not as unreachable or read-only
    assert result.exit_code == 1, result.output
    assert f"{uri} answers, but not as an MLflow tracking server" in result.output
    assert "Traceback" not in result.output
    # ... and it was only ever asked, never told to change anything
    assert seen and all(line.startswith("GET ") for line in seen), seen
    # and: a reader is told the same
    with pytest.raises(store.NotMlflow, match="answers, but not as an MLflow tracking server"):
        store.connect(uri)


def _store_with_two_versions(tmp_path: Path, uri: str) -> None:
    """needle-force-30 v1 and v2, v2 the champion that replaced v1."""
    client = MlflowClient(tracking_uri=uri, registry_uri=uri)
    name = model_name(30)
    client.create_registered_model(name)
    for v in (1, 2):
        source = tmp_path / f"v{v}"
        source.mkdir()
        client.create_model_version(name, source.as_uri(), tags={store.FORMAT_TAG: DEPLOY_FORMAT})
    client.set_registered_model_alias(name, CHAMPION, "2")
    client.set_model_version_tag(name, "2", f"{TAG}previous_champion", "1")


def test_a_read_only_store_is_read_but_refuses_a_rollback_before_the_alias_moves(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # given: a store whose champion v2 replaced v1, opened read-only (SQLite's mode=ro)
    # (MLflow makes a folder named after that URI's path, "file:/tmp/...", in the cwd: keep it in tmp_path)
    monkeypatch.chdir(tmp_path)
    db = tmp_path / "mlflow.db"
    _store_with_two_versions(tmp_path, f"sqlite:///{db}")
    read_only = f"sqlite:///file:{db}?mode=ro&uri=true"
    # when: a reader connects, and a writer
    reader = store.connect(read_only, must_exist=True)
    with pytest.raises(store.ReadOnlyStore, match="is read-only here") as refused:
        store.connect(read_only, write=True)
    # then: the reader sees the champion; the writer is told it is read-only, not unreachable
    assert str(store.alias_version(reader, model_name(30), CHAMPION).version) == "2"
    assert "not MLflow" not in str(refused.value)
    # when: `needlecue rollback 30` on it
    monkeypatch.setenv("MLFLOW_TRACKING_URI", read_only)
    result = CliRunner().invoke(app, ["rollback", "30"])
    # then: exit 1 saying read-only (no traceback), and the champion is still v2
    assert result.exit_code == 1 and "read-only" in result.output, result.output
    assert "Traceback" not in result.output
    writable = MlflowClient(tracking_uri=f"sqlite:///{db}", registry_uri=f"sqlite:///{db}")
    assert str(writable.get_model_version_by_alias(model_name(30), CHAMPION).version) == "2"
    # and: on the same store writable, the rollback goes through
    assert versions.rollback(30, uri=f"sqlite:///{db}") == (2, 1)


@pytest.mark.parametrize(
    "not_mlflow", [(503, PAGE), (401, PAGE)], ids=["503: down for now", "401: credentials"], indirect=True
)
def test_a_server_error_or_a_refused_login_is_unreachable_not_another_service(not_mlflow) -> None:
    # given: a server answering 503 (a proxy before a stopped MLflow) or 401 (a login) to everything
    uri, _ = not_mlflow
    # when: a reader connects
    with pytest.raises(store.RegistryUnreachable, match="cannot reach the MLflow registry") as failed:
        store.connect(uri)
    # then: unreachable (try again, or with credentials), not "not MLflow"
    assert type(failed.value) is store.RegistryUnreachable


def _other_database(db: Path) -> None:
    with closing(sqlite3.connect(db)) as con:
        con.execute("CREATE TABLE patients (id INTEGER PRIMARY KEY, name TEXT)")
        con.commit()


@pytest.mark.parametrize(
    ("make", "must_exist", "says"),
    [
        (_other_database, False, "is not an MLflow database (tables: patients)"),
        (lambda db: db.write_bytes(b"t_s,fx,fy,fz\n" * 40), False, "is not an SQLite database"),
        (lambda db: db.write_bytes(b""), True, "is not an MLflow database (tables: none)"),
    ],
    ids=["another program's database", "not a database", "empty file, for a reader"],
)
def test_a_sqlite_file_that_is_not_an_mlflow_store_is_refused_and_left_as_it_is(
    tmp_path: Path, make, must_exist: bool, says: str
) -> None:
    # given: a file at the store's path that is not an MLflow store
    db = tmp_path / "mlflow.db"
    make(db)
    before = db.read_bytes()
    # when: connecting to it (as a writer, or as a reader for the empty file)
    with pytest.raises(store.NotMlflow, match=re.escape(says)):
        store.connect(f"sqlite:///{db}", must_exist=must_exist, write=not must_exist)
    # then: refused, and not a byte of it changed (MLflow never added its tables)
    assert db.read_bytes() == before


@pytest.mark.parametrize(
    ("uri", "says"),
    [
        ("ftp://127.0.0.1/mlflow", "ftp"),
        ("postgresql+nosuchdriver://lab@127.0.0.1:1/mlflow", "nosuchdriver"),
    ],
    ids=["unknown scheme", "missing database driver"],
)
def test_a_tracking_uri_mlflow_cannot_use_is_unreachable_with_its_reason(uri: str, says: str) -> None:
    # given: a tracking URI MLflow cannot open at all
    # when: connecting
    with pytest.raises(store.RegistryUnreachable) as failed:
        store.connect(uri)
    # then: one error naming the URI and why, not MLflow's or SQLAlchemy's own exception
    assert uri in str(failed.value) and says in str(failed.value)


def test_only_a_finished_run_is_reused(mlflow_store: str) -> None:
    # given: three runs with the same tag, one left running, one failed, one finished in between
    client = MlflowClient(tracking_uri=mlflow_store)
    exp_id = store.experiment_id(client)
    tag = f"{TAG}deploy_sha256"
    runs = [client.create_run(exp_id, tags={tag: "abc"}) for _ in range(3)]
    client.set_terminated(runs[0].info.run_id, "FAILED")
    client.set_terminated(runs[1].info.run_id, "FINISHED")
    # when / then: the finished one is the answer, not the later running one
    assert store.finished_run(client, exp_id, tag, "abc").info.run_id == runs[1].info.run_id
    # and: nothing finished with another value
    assert store.finished_run(client, exp_id, tag, "other") is None


def test_connecting_and_using_the_fluent_api_leave_mlflows_globals_as_they_were(
    mlflow_store: str, tmp_path: Path
) -> None:
    # given: MLflow's URIs from the environment (the autouse store), not set in the process
    import os

    import mlflow

    other = f"sqlite:///{tmp_path / 'other.db'}"
    env = {
        k: os.environ.get(k)
        for k in ("MLFLOW_TRACKING_URI", "MLFLOW_REGISTRY_URI", *mlflow_env.HTTP_SETTINGS)
    }
    # when: a writer connects to another store and logs a run there through the fluent API
    client = store.connect(other, write=True)
    with mlflow_env.patience(write=True), mlflow_env.fluent(client.tracking_uri):
        assert os.environ["MLFLOW_HTTP_REQUEST_TIMEOUT"] == mlflow_env.WRITE_TIMEOUT_S
        with mlflow.start_run(experiment_id=store.experiment_id(client)) as run:
            mlflow.log_metric("m", 1.0)
    # then: the run is in the other store, and the environment and MLflow's URIs are as before
    assert client.get_run(run.info.run_id).data.metrics == {"m": 1.0}
    assert {k: os.environ.get(k) for k in env} == env
    assert mlflow.get_tracking_uri() == mlflow_store
    os.environ["MLFLOW_TRACKING_URI"] = other  # still read from the environment: nothing pinned
    assert mlflow.get_tracking_uri() == other
    os.environ["MLFLOW_TRACKING_URI"] = mlflow_store


def test_the_experiments_open_on_model_training_in_the_ui(mlflow_store: str) -> None:
    # given: an experiment made before needlecue tagged its kind
    client = MlflowClient(tracking_uri=mlflow_store)
    client.create_experiment(store.EXPERIMENT)
    # when: a writer uses it
    exp_id = store.experiment_id(client)
    # then: it carries MLflow's experiment kind for model training, as a new one does
    assert client.get_experiment(exp_id).tags[store.KIND_TAG] == "custom_model_development"
    new = store.experiment_id(client, store.UNIT_EXPERIMENT, store.UNIT_ABOUT)
    assert client.get_experiment(new).tags[store.KIND_TAG] == "custom_model_development"


def test_environment_blocks_that_end_out_of_order_restore_the_environment(monkeypatch) -> None:
    # given: a timeout the user set, and two polls on two threads, each in its own block
    monkeypatch.setenv("MLFLOW_HTTP_REQUEST_TIMEOUT", "30")
    first, second = (
        mlflow_env.environment({"MLFLOW_HTTP_REQUEST_TIMEOUT": "2"}),
        mlflow_env.environment({"MLFLOW_HTTP_REQUEST_TIMEOUT": "2"}),
    )
    # when: the second starts before the first ends, and ends after it
    first.__enter__()
    second.__enter__()
    first.__exit__(None, None, None)
    during = os.environ["MLFLOW_HTTP_REQUEST_TIMEOUT"]
    second.__exit__(None, None, None)
    # then: the open block keeps its value, and the user's comes back when none is open
    assert during == "2"
    assert os.environ["MLFLOW_HTTP_REQUEST_TIMEOUT"] == "30"


def test_nested_environment_blocks_restore_each_level_and_patience_reads_the_users_value(monkeypatch) -> None:
    # given: no timeout set by the user
    monkeypatch.delenv("MLFLOW_HTTP_REQUEST_TIMEOUT", raising=False)
    # when: a writer's patience opens while a poll's block is open (another thread's), and inside it
    # one more block
    with mlflow_env.environment({"MLFLOW_HTTP_REQUEST_TIMEOUT": "2"}):
        with mlflow_env.patience(write=True):
            writer = os.environ["MLFLOW_HTTP_REQUEST_TIMEOUT"]
            with mlflow_env.environment({"MLFLOW_HTTP_REQUEST_TIMEOUT": "5"}):
                inner = os.environ["MLFLOW_HTTP_REQUEST_TIMEOUT"]
            after_inner = os.environ["MLFLOW_HTTP_REQUEST_TIMEOUT"]
        after_writer = os.environ["MLFLOW_HTTP_REQUEST_TIMEOUT"]
    # then: the writer gets its own 60 s, not the poll's 2 s; each level comes back as it ends
    assert (writer, inner, after_inner) == (mlflow_env.WRITE_TIMEOUT_S, "5", mlflow_env.WRITE_TIMEOUT_S)
    assert after_writer == "2"
    assert "MLFLOW_HTTP_REQUEST_TIMEOUT" not in os.environ
