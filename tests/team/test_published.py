"""Champions published out of the tracking server's path: the stack's publisher keeps the published bucket
up to date, simulators fetch and poll it with read-only keys, and nothing unsigned or changed runs.

Runs after test_lab_flow.py on the same stack and project (one xdist group, file order)."""

from __future__ import annotations

import contextlib
import http.client
import json
import logging
import subprocess
import time
from pathlib import Path

import boto3
import mlflow
import pytest
from botocore.config import Config
from botocore.exceptions import ClientError
from typer.testing import CliRunner

from needlecue_client import ForceClient, fetch
from needlecue_client.cache import poll_alias
from needlecue_client.model import Model
from needlecue_client.published import PublishedRefused, default_location
from needlecue_runtime.registry import manifest as signed
from needlecue_runtime.registry import store
from pipeline.cli import app
from pipeline.team import publish

pytestmark = [pytest.mark.team, pytest.mark.xdist_group("team")]
NAME = "needle-force-15"
UNIT = "est-sim-101"
# the lab project's models (other team tests register models of their own into the same stack)
LAB_MODELS = ["needle-force-15", "needle-force-45", f"needle-unit-{UNIT}"]
ONLY_LAB = [arg for name in LAB_MODELS for arg in ("--model", name)]


def _publish(team, lab: Path, *args: str) -> subprocess.CompletedProcess:
    """`needlecue team publish` in the lab's folder, run in this process (a process of its own would
    only import MLflow and boto3 again: about 3 s each, ten times in this file)."""
    cmd = ["team", "publish", "--dir", str(team.dir), *args]
    with contextlib.chdir(lab):
        done = CliRunner().invoke(app, cmd)
    if done.exception is not None and not isinstance(done.exception, SystemExit):
        raise done.exception  # a crash, not the command's own error
    return subprocess.CompletedProcess(cmd, done.exit_code, done.stdout, done.stderr)


def _up_to_date(team, lab: Path, within_s: float = 60.0) -> subprocess.CompletedProcess:
    """`publish --check` until it passes (the publisher works on its own), at most `within_s`."""
    deadline = time.monotonic() + within_s
    while True:
        done = _publish(team, lab, "--check", *ONLY_LAB)
        if done.returncode == 0 or time.monotonic() > deadline:
            return done
        time.sleep(1)


def _s3(team, keys: dict[str, str]):
    return boto3.client(
        "s3", endpoint_url=team.s3_endpoint, aws_access_key_id=keys["access_key"],
        aws_secret_access_key=keys["secret_key"], region_name="us-east-1",
        config=Config(retries={"max_attempts": 1}),
    )  # fmt: skip


def _lab_s3(team):
    return _s3(team, team.settings["s3"])


def _registry_champion(team) -> str:
    with team.as_lab():
        client = store.connect(team.tracking_uri)
        return str(store.alias_version(client, NAME, store.CHAMPION).version)


def test_the_publisher_publishes_every_alias_and_publishing_again_changes_nothing(team, lab):
    # Given the lab's registry (champions of 15° and 45°, a unit's calibration), published by the stack's
    # publisher on its own
    checked = _up_to_date(team, lab)
    # Then `publish --check` finds nothing out of date ...
    assert checked.returncode == 0, checked.stdout + checked.stderr
    assert "up to date" in checked.stdout
    # ... the bucket holds a manifest per model and alias, and every object a manifest names
    s3 = _lab_s3(team)
    keys = {o["Key"] for o in s3.list_objects_v2(Bucket="published")["Contents"]}
    published = [("needle-force-15", "champion"), ("needle-force-45", "champion")]
    for name, alias in [*published, (f"needle-unit-{UNIT}", "current")]:
        assert signed.manifest_key(name, alias) in keys
        doc = json.loads(
            s3.get_object(Bucket="published", Key=signed.manifest_key(name, alias))["Body"].read()
        )
        assert {signed.object_key(f["sha256"]) for f in doc["manifest"]["files"].values()} <= keys
    before = {o["Key"]: o["ETag"] for o in s3.list_objects_v2(Bucket="published")["Contents"]}
    # When the lab publishes by hand
    again = _publish(team, lab, *ONLY_LAB)
    # Then nothing changes: not one object or manifest is written again
    assert again.returncode == 0 and "up to date" in again.stdout, again.stdout + again.stderr
    after = {o["Key"]: o["ETag"] for o in s3.list_objects_v2(Bucket="published")["Contents"]}
    assert after == before


def test_a_simulators_keys_read_the_published_bucket_and_nothing_else(team):
    # Given a simulator's S3 keys
    sim = _s3(team, team.settings["s3_reader"])
    # Then it reads and lists the published bucket
    key = signed.manifest_key(NAME, store.CHAMPION)
    assert sim.get_object(Bucket="published", Key=key)["Body"].read()
    # and it may not write or delete there, nor read the other buckets
    refused = []
    for call in (
        lambda: sim.put_object(Bucket="published", Key=key, Body=b"{}"),
        lambda: sim.delete_object(Bucket="published", Key=key),
        lambda: sim.list_objects_v2(Bucket="mlflow"),
        lambda: sim.list_objects_v2(Bucket="dvc"),
    ):
        with pytest.raises(ClientError) as e:
            call()
        refused.append(e.value.response["Error"]["Code"])
    assert refused == ["AccessDenied"] * 4


def test_a_simulator_fetches_the_champion_and_its_unit_with_the_tracking_server_stopped(
    team, lab, as_role, tmp_path
):
    # Given a simulator's environment (the published bucket) and the tracking server stopped
    assert _up_to_date(team, lab).returncode == 0
    champion = _registry_champion(team)
    as_role("simulator", published=True)
    assert default_location() == f"published+{team.published_url}"
    team.stop_one("mlflow")
    try:
        # When it starts a client for a unit
        client = ForceClient.from_registry(15, unit_id=UNIT, cache_dir=tmp_path / "cache", poll_s=None)
        # Then it runs the current champion, calibrated for the unit, fetched from the bucket
        assert client.version["version"] == champion
        assert client.version["tracking_uri"].startswith("published+")
        assert client.calibrated and client.has_cues
    finally:
        team.start_one("mlflow")


def test_a_poll_is_one_conditional_get_answered_304(team, lab, as_role, monkeypatch):
    # Given a simulator that has polled its champion once, and its S3 requests counted from now
    as_role("simulator", published=True)
    uri = default_location()
    first = poll_alias(NAME, store.CHAMPION, uri)
    answers: list[int] = []
    receive = http.client.HTTPConnection.getresponse

    def counted(self):
        answer = receive(self)
        answers.append(answer.status)
        return answer

    monkeypatch.setattr(http.client.HTTPConnection, "getresponse", counted)
    # When it polls again, nothing having changed
    again = poll_alias(NAME, store.CHAMPION, uri)
    # Then it sent one request, answered 304, and knows where the champion points
    assert answers == [304]
    assert (again.version, again.source) == (first.version, first.source)


def _fetch_fresh(uri: str, folder: Path) -> Path:
    return fetch(15, cache_dir=folder, tracking_uri=uri)


def test_nothing_changed_or_unsigned_runs_and_the_verified_copy_keeps_running(
    team, lab, as_role, tmp_path, caplog
):
    # Given a simulator with a verified copy of the champion, and the lab's access to the bucket
    assert _up_to_date(team, lab).returncode == 0
    as_role("simulator", published=True)
    uri = default_location()
    cache = tmp_path / "cache"
    kept = _fetch_fresh(uri, cache)
    s3, key = _lab_s3(team), signed.manifest_key(NAME, store.CHAMPION)
    original = s3.get_object(Bucket="published", Key=key)["Body"].read()
    doc = json.loads(original)
    onnx = doc["manifest"]["files"]["model.onnx"]
    onnx_bytes = s3.get_object(Bucket="published", Key=signed.object_key(onnx["sha256"]))["Body"].read()
    other_key = signed.new_private_key()
    changed = {**doc, "manifest": {**doc["manifest"], "version": "999"}}
    client_log = logging.getLogger("needlecue_client")
    client_log.addHandler(caplog.handler)  # directly: an entry point's setup may stop propagation
    cases = {
        "a changed manifest": (json.dumps(changed).encode(), None, "changed after signing"),
        "an unsigned manifest": (json.dumps({"manifest": doc["manifest"]}).encode(), None, "unsigned"),
        "another key's manifest": (
            json.dumps(signed.sign({**doc["manifest"], "version": "999"}, other_key)).encode(),
            None,
            "signed by another key",
        ),
        "a changed object": (original, onnx_bytes[:-1] + bytes([onnx_bytes[-1] ^ 1]), "changed or damaged"),
    }
    try:
        for case, (manifest_bytes, object_bytes, why) in cases.items():
            # When the bucket holds it
            s3.put_object(Bucket="published", Key=key, Body=manifest_bytes)
            if object_bytes is not None:
                s3.put_object(Bucket="published", Key=signed.object_key(onnx["sha256"]), Body=object_bytes)
            # Then a simulator without a copy refuses it, saying why
            with pytest.raises(PublishedRefused, match=why):
                _fetch_fresh(uri, tmp_path / f"fresh-{len(why)}")
            # and one with a verified copy keeps running that copy (a refused manifest is logged as an
            # error; a changed object is not even fetched: the copy's own files are the manifest's)
            caplog.clear()
            assert _fetch_fresh(uri, cache) == kept
            logged = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
            assert any(why in m for m in logged) == (object_bytes is None), (case, logged)
            assert Model.open(kept).version["version"] == doc["manifest"]["version"]  # checked as it opens
            s3.put_object(Bucket="published", Key=key, Body=original)
            s3.put_object(Bucket="published", Key=signed.object_key(onnx["sha256"]), Body=onnx_bytes)
    finally:
        client_log.removeHandler(caplog.handler)
        s3.put_object(Bucket="published", Key=key, Body=original)
        s3.put_object(Bucket="published", Key=signed.object_key(onnx["sha256"]), Body=onnx_bytes)
    # And a changed manifest is found out of date by `publish --check`, and published again
    s3.put_object(Bucket="published", Key=key, Body=json.dumps(changed).encode())
    stale = _publish(team, lab, "--check", *ONLY_LAB)
    assert stale.returncode == 1 and "its manifest is refused" in stale.stdout, stale.stdout + stale.stderr
    assert _publish(team, lab, *ONLY_LAB).returncode == 0
    assert _publish(team, lab, "--check", *ONLY_LAB).returncode == 0


def test_a_champion_moved_by_the_lab_reaches_a_polling_simulator_through_the_webhook(
    team, lab, as_role, tmp_path
):
    # Given a simulator's client polling the published bucket every second
    assert _up_to_date(team, lab).returncode == 0
    as_role("simulator", published=True)
    client = ForceClient.from_registry(15, unit_id=UNIT, cache_dir=tmp_path / "cache", poll_s=1.0)
    old = client.version["version"]
    # When the lab makes another version champion (only the registry is told: the webhook does the rest)
    as_role("lab")
    with store.writing() as lab_client:
        champion = store.alias_version(lab_client, NAME, store.CHAMPION)
        new = mlflow.register_model(champion.source, NAME, tags=champion.tags)
        lab_client.set_registered_model_alias(NAME, store.CHAMPION, new.version)
    moved = time.monotonic()
    # Then, polling between insertions, the client runs the new champion, still calibrated
    as_role("simulator", published=True)
    while client.version["version"] != new.version and time.monotonic() - moved < 60:
        time.sleep(0.2)
        client.reset()
    took = time.monotonic() - moved
    assert client.version["version"] == new.version != old, f"not there after {took:.1f} s"
    assert client.calibrated
    print(f"champion moved -> running on a client polling every 1 s: {took:.2f} s")
    # And the publisher did it: the bucket is up to date without anyone publishing by hand
    assert _publish(team, lab, "--check", *ONLY_LAB).returncode == 0


def test_publish_says_what_is_out_of_date_without_a_stack_of_its_own(team, lab):
    # Given the bucket up to date, then a manifest deleted behind the publisher's back
    assert _up_to_date(team, lab).returncode == 0
    s3 = _lab_s3(team)
    key = signed.manifest_key("needle-force-45", store.CHAMPION)
    s3.delete_object(Bucket="published", Key=key)
    # When the lab plans against the registry
    with team.as_lab():
        changes = publish.plan(store.connect(team.tracking_uri), publish.Target.of(team), LAB_MODELS)
    # Then exactly that alias is out of date, as not published
    assert [(c.name, c.alias, c.why) for c in changes] == [("needle-force-45", "champion", "not published")]
    assert _publish(team, lab, *ONLY_LAB).returncode == 0


def test_a_broken_version_is_not_published_and_does_not_hold_up_the_others(team, lab, as_role):
    # Given a champion whose version has no model files, and a published manifest deleted
    as_role("lab")
    with store.writing() as client:
        run = client.create_run(store.experiment_id(client, "publish-check", "a run with no model files"))
        store.create_registered_model(client, "needle-force-75", "a broken version")
        version = client.create_model_version(
            "needle-force-75", f"runs:/{run.info.run_id}/model", run.info.run_id
        )
        client.set_registered_model_alias("needle-force-75", store.CHAMPION, version.version)
    _lab_s3(team).delete_object(
        Bucket="published", Key=signed.manifest_key("needle-force-45", store.CHAMPION)
    )
    try:
        # When the lab publishes everything
        done = _publish(team, lab)
        # Then the broken version is refused, saying why, the other alias is published anyway, and the
        # command says it failed
        assert done.returncode == 1, done.stdout + done.stderr
        assert "cannot publish: needle-force-75@champion: v1 not published" in done.stdout
        assert "published: needle-force-45@champion" in done.stdout
        assert _publish(team, lab, "--check", *ONLY_LAB).returncode == 0
    finally:
        with store.writing() as client:
            client.delete_registered_model("needle-force-75")
