"""The team stack as systemd services (`needlecue team units`): a unit per server, written from the
settings and the commands `team start` runs, restarted on failure, secrets outside the units, and
accepted by `systemd-analyze verify`."""

from __future__ import annotations

import os
import pwd
import shlex
import shutil
import stat
import subprocess
from pathlib import Path

import pytest
from typer.testing import CliRunner

from pipeline.cli import app
from pipeline.team.services import TARGET, env_file, unit_name, write_units
from pipeline.team.stack import SERVERS, Stack

pytestmark = [pytest.mark.team, pytest.mark.xdist_group("team")]
needs_systemd = pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="needs systemd-analyze")


def verify(files: list[Path]) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        ["systemd-analyze", "verify", *map(str, files)],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )


def fields(unit: Path) -> dict[str, list[str]]:
    out: dict[str, list[str]] = {}
    for line in unit.read_text().splitlines():
        key, sep, value = line.partition("=")
        if sep and not line.startswith("#"):
            out.setdefault(key, []).append(value)
    return out


@needs_systemd
def test_a_unit_per_server_runs_what_team_start_runs_and_systemd_accepts_them(tmp_path: Path) -> None:
    # given: a stack's settings (no server started)
    stack = Stack(tmp_path / "stack")
    stack.init(base_port=21000)
    # when: its units are written
    written = write_units(stack, tmp_path / "units")
    # then: a unit per server and the target, each the foreground command of `team start`'s launch,
    # restarted on failure, ordered after what it needs; systemd's own checker accepts them all
    assert sorted(p.name for p in written) == sorted([*(unit_name(s) for s in SERVERS), TARGET])
    for server in SERVERS:
        f = fields(tmp_path / "units" / unit_name(server))
        launch = stack.launch(server)
        assert f["ExecStart"] == [shlex.join(launch.cmd)] and f["WorkingDirectory"] == [str(launch.cwd)]
        assert f["Restart"] == ["on-failure"] and f["WantedBy"] == [TARGET]
        # a system unit runs as root unless told: each names its user (postgres's own under root)
        assert f["User"] == [launch.user or pwd.getpwuid(os.geteuid()).pw_name]
    assert (
        "needlecue-team-postgres.service" in fields(tmp_path / "units" / unit_name("mlflow"))["Requires"][0]
    )
    done = verify(written)
    assert done.returncode == 0, done.stderr
    # and: the secrets are in environment files only the stack's owner reads, never in a unit
    secrets = [stack.settings["postgres_password"], stack.settings["s3"]["secret_key"]]
    assert not any(s in p.read_text() for p in written for s in secrets)
    mlflow_env = env_file(stack, "mlflow")
    assert stat.S_IMODE(mlflow_env.stat().st_mode) == 0o600
    assert f'MLFLOW_BACKEND_STORE_URI="{stack.database_uri("mlflow")}"' in mlflow_env.read_text()


@needs_systemd
def test_the_checker_refuses_a_broken_unit(tmp_path: Path) -> None:
    # given: a unit whose program does not exist (so the check above can fail)
    stack = Stack(tmp_path / "stack")
    stack.init(base_port=21000)
    unit = write_units(stack, tmp_path / "units")[0]
    unit.write_text(unit.read_text().replace("ExecStart=", "ExecStart=/nonexistent/postgres-9 "))
    # then: systemd-analyze says so
    done = verify([unit])
    assert done.returncode != 0 and "/nonexistent/postgres-9" in done.stderr


def test_the_command_needs_a_started_stack_and_says_so(tmp_path: Path) -> None:
    # given: settings, but PostgreSQL never initialised (`team start` never ran)
    stack = Stack(tmp_path / "stack")
    stack.init(base_port=21000)
    # when / then: one line saying what to do first, and nothing written
    out = CliRunner().invoke(app, ["team", "units", "--dir", str(stack.dir), "--out", str(tmp_path / "u")])
    assert out.exit_code == 1 and "run `needlecue team start` once first" in out.output
    assert not (tmp_path / "u").exists()
