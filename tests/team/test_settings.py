"""A stack's settings and each role's environment, without starting a server: the keys a simulator
holds for the published bucket, and a stack made before publishing gaining them."""

from __future__ import annotations

import base64
import json
import shutil
from types import SimpleNamespace

import pytest
from typer.testing import CliRunner

from needlecue_runtime.registry import manifest as signed
from pipeline.cli import app
from pipeline.team.servers.base import StackError
from pipeline.team.stack import SERVERS, Stack

pytestmark = [pytest.mark.team, pytest.mark.xdist_group("team")]


def test_a_simulator_gets_the_bucket_read_only_keys_and_the_public_half_only(tmp_path):
    # Given a new stack's settings
    stack = Stack(tmp_path / "stack")
    stack.init(base_port=21000)
    s = stack.settings
    # When a simulator's environment is made
    env = stack.role_env("simulator")
    # Then it reads the published bucket with the reader's keys and checks with the public key ...
    assert env["NEEDLECUE_PUBLISHED_URL"] == "http://127.0.0.1:21001/published"
    assert env["AWS_ACCESS_KEY_ID"] == s["s3_reader"]["access_key"] != s["s3"]["access_key"]
    public = signed.public_key(env["NEEDLECUE_PUBLISH_PUBLIC_KEY"])
    assert public == signed.public_of(base64.b64decode(s["publish_private_key"]))
    # ... and holds neither the lab's S3 keys nor the signing key
    assert s["s3"]["secret_key"] not in env.values()
    assert s["publish_private_key"] not in env.values()
    # And the lab's environment is the lab's keys, without the bucket (it reads the registry)
    lab = stack.role_env("lab")
    assert lab["AWS_ACCESS_KEY_ID"] == s["s3"]["access_key"] and "NEEDLECUE_PUBLISHED_URL" not in lab


def test_a_stack_made_before_publishing_gains_its_keys_and_keeps_its_credentials(tmp_path):
    # Given a team.json written before publishing existed
    stack = Stack(tmp_path / "stack")
    stack.init(base_port=21000)
    old = {k: v for k, v in stack.settings.items() if k not in ("s3_reader", "publish_private_key")}
    stack.file.write_text(json.dumps(old))
    # When it is started again (init runs first)
    assert stack.init() is False
    # Then it has a reader and a signing key, and every credential it had is the same
    now = stack.settings
    assert {"s3_reader", "publish_private_key"} <= set(now)
    assert {k: now[k] for k in old} == old
    assert oct(stack.file.stat().st_mode & 0o777) == "0o600"


def test_publish_without_a_stack_says_where_it_looked(tmp_path):
    # When the lab publishes from a folder holding no stack
    result = CliRunner().invoke(app, ["team", "publish", "--check", "--dir", str(tmp_path / "none")])
    # Then it fails, naming the folder and how to start one
    assert result.exit_code == 1
    assert "no team stack in" in result.output and "needlecue team start" in result.output


def _disk(monkeypatch, free_gib: float, total_gib: float = 250) -> None:
    """The disk under the stack as `shutil.disk_usage` reports it."""
    gib = 2**30
    usage = SimpleNamespace(
        total=int(total_gib * gib), used=int((total_gib - free_gib) * gib), free=int(free_gib * gib)
    )
    monkeypatch.setattr(shutil, "disk_usage", lambda _path: usage)


def test_a_stack_on_a_disk_seaweedfs_would_not_write_to_refuses_to_start_and_says_why(tmp_path, monkeypatch):
    # Given a stack whose disk has 2 GiB free of 250 (SeaweedFS writes nothing below 1 %: 2.5 GiB)
    stack = Stack(tmp_path / "stack")
    stack.init(base_port=21000)
    _disk(monkeypatch, free_gib=2)
    # When it is started
    with pytest.raises(StackError) as refused:
        stack.start(progress=lambda _m: None)
    # Then nothing starts, and the error says how much is free, where, and the line
    assert "2.0 GiB free on the disk of" in str(refused.value) and str(stack.dir) in str(refused.value)
    assert "refuses every write below 2.5 GiB" in str(refused.value)
    assert not any(stack.running(server) for server in SERVERS)
    # And `team status` says so and fails
    result = CliRunner().invoke(app, ["team", "status", "--dir", str(stack.dir)])
    assert result.exit_code == 1 and "error: s3: 2.0 GiB free" in result.output


def test_a_disk_close_to_that_line_is_a_warning_and_room_enough_is_silent(tmp_path, monkeypatch):
    # Given a stack
    stack = Stack(tmp_path / "stack")
    stack.init(base_port=21000)
    # When its disk has 1 GiB more than SeaweedFS's line, then 100 GiB free
    _disk(monkeypatch, free_gib=3.5)
    close = stack.disk_space()
    _disk(monkeypatch, free_gib=100)
    roomy = stack.disk_space()
    # Then the first is low but writable, the second neither
    assert (close.full, close.low, roomy.full, roomy.low) == (False, True, False, False)
    assert close.describe().endswith("close to it") and not roomy.describe().endswith("close to it")
