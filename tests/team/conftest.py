"""One real team stack (PostgreSQL, SeaweedFS, MLflow with basic auth) on loopback for the tests of this
folder, on free ports, in a temp folder; stopped and deleted at the end. All run on one xdist worker
(group "team"), one after another in file order."""

from __future__ import annotations

import shutil
from collections.abc import Iterator

import pytest

from pipeline.team.stack import SERVERS, Stack, free_base_port


def pytest_runtest_setup(item: pytest.Item) -> None:
    """Under `--dist loadgroup` xdist marks each grouped test's id with its group; without the mark the
    group is ignored and each worker would start a stack and a project of its own (pytest 9.2 with
    xdist 3.8: pytest-xdist issue #1386). Fail before anything starts instead."""
    if getattr(item.config.option, "loadgroup", False) and not item.nodeid.endswith("@team"):
        pytest.fail(f"{item.nodeid}: xdist did not keep the team tests on one worker (pytest-xdist #1386)")


@pytest.fixture(scope="session")
def team(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Stack]:
    stack = Stack(tmp_path_factory.mktemp("team") / "stack")
    stack.init(base_port=free_base_port())
    try:
        stack.start(progress=lambda _m: None)
        yield stack
    finally:
        try:
            stack.stop()
            # the servers' logs outlive the stack, in the session's temp folder (pytest keeps the last 3)
            kept = tmp_path_factory.getbasetemp() / "team-logs"
            kept.mkdir(exist_ok=True)
            for log in (stack.log(server) for server in SERVERS):
                if log.is_file():  # a stack that failed to start may lack some
                    shutil.copy2(log, kept)
        finally:
            stack.stop(purge=True)


@pytest.fixture
def as_role(team: Stack, monkeypatch: pytest.MonkeyPatch):
    """as_role("lab") puts that role's environment (MLflow URI and credentials) in place."""

    def use(role: str) -> dict[str, str]:
        env = team.role_env(role)
        for key in ("AWS_ACCESS_KEY_ID", "AWS_SECRET_ACCESS_KEY"):
            monkeypatch.delenv(key, raising=False)
        for key, value in env.items():
            monkeypatch.setenv(key, value)
        monkeypatch.setenv("MLFLOW_REGISTRY_URI", env["MLFLOW_TRACKING_URI"])
        return env

    return use
