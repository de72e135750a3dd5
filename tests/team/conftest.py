"""One real team stack (PostgreSQL, SeaweedFS, MLflow with basic auth) on loopback for the tests of this
folder, on free ports, in a temp folder; stopped and deleted at the end. All run on one xdist worker
(group "team"), one after another in file order."""

from __future__ import annotations

import shutil
from collections.abc import Iterator
from pathlib import Path

import pytest

from needlecue_client.published import PUBLISHED_ENV
from pipeline.team.stack import SERVERS, Stack, free_base_port
from tests.projects import built_stages, copy_project, run


def pytest_runtest_setup(item: pytest.Item) -> None:
    """Under `--dist loadgroup` xdist marks each grouped test's id with its group; without the mark the
    group is ignored and each worker would start a stack and a project of its own (pytest 9.2 with
    xdist 3.8: pytest-xdist issue #1386). Fail before anything starts instead."""
    if getattr(item.config.option, "loadgroup", False) and not item.nodeid.endswith("@team"):
        pytest.fail(f"{item.nodeid}: xdist did not keep the team tests on one worker (pytest-xdist #1386)")


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo) -> Iterator[None]:
    """A failed test that used the stack reports the stack's disk and its servers' last errors: CI keeps
    no logs, and S3's "InternalError" or MLflow's "500" alone do not say why."""
    outcome = yield
    report = outcome.get_result()
    stack = getattr(item, "funcargs", {}).get("team")
    if report.when == "call" and report.failed and isinstance(stack, Stack):
        report.sections.append(("team stack", _diagnosis(stack)))


def _diagnosis(stack: Stack, n: int = 8) -> str:
    lines = [stack.disk_space().describe()]
    for server in ("s3", "mlflow", "publisher"):
        log = stack.log(server)
        text = log.read_text(errors="replace").splitlines() if log.is_file() else []
        # SeaweedFS marks its errors "E<date>"; MLflow and the publisher write ERROR or a traceback
        errors = [line for line in text if line[:2] in {"E0", "E1"} or "ERROR" in line or "Error" in line]
        lines += [
            f"--- {server}: last {min(n, len(errors))} of {len(errors)} error lines ({log})",
            *errors[-n:],
        ]
    return "\n".join(lines)


@pytest.fixture(scope="session")
def team(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Stack]:
    stack = Stack(tmp_path_factory.mktemp("team") / "stack")
    # rounds on webhook calls only: a timed round would repair what a test tampers with, mid-test
    stack.init(base_port=free_base_port(), publish_every_s=3600)
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
    """as_role("lab") puts that role's environment (MLflow URI and credentials) in place; a simulator's
    published bucket only with `published=True`."""

    def use(role: str, published: bool = False) -> dict[str, str]:
        env = team.role_env(role)
        if not published:  # the tracking server's own path (a simulator's client would take the bucket)
            env.pop(PUBLISHED_ENV, None)
        for key in ("AWS_ACCESS_KEY_ID", "AWS_SECRET_ACCESS_KEY", PUBLISHED_ENV):
            monkeypatch.delenv(key, raising=False)
        for key, value in env.items():
            monkeypatch.setenv(key, value)
        monkeypatch.setenv("MLFLOW_REGISTRY_URI", env["MLFLOW_TRACKING_URI"])
        return env

    return use


def lab_env(team, role: str) -> dict[str, str]:
    env = team.role_env(role)
    return {**env, "MLFLOW_REGISTRY_URI": env["MLFLOW_TRACKING_URI"], "GIT_AUTHOR_NAME": "lab",
            "GIT_AUTHOR_EMAIL": "lab@example.org", "GIT_COMMITTER_NAME": "lab",
            "GIT_COMMITTER_EMAIL": "lab@example.org"}  # fmt: skip


@pytest.fixture(scope="session")
def lab(team, tiny_built, tmp_path_factory) -> Path:
    """A small git + DVC project whose default remote is the stack's S3 store, reproduced as the lab
    (from the shared build: only register runs, into the server). Shared by the team tests."""
    root, _ = copy_project(tiny_built, tmp_path_factory.mktemp("lab") / "project")
    env = lab_env(team, "lab")
    run(root, "git", "init", "-q", env=env)
    run(root, "dvc", "config", "core.no_scm", "false", env=env)
    # (re)writes each output's .gitignore entry, so no data goes into git
    run(root, "dvc", "commit", "-f", "-q", *built_stages(root), env=env)
    run(root, "dvc", "remote", "add", "-d", "team", "s3://dvc/needlecue", env=env)
    run(root, "dvc", "remote", "modify", "team", "endpointurl", team.s3_endpoint, env=env)
    run(root, "git", "add", "-A", env=env)
    run(root, "git", "commit", "-q", "-m", "a lab's project", env=env)
    run(root, "dvc", "repro", env=env)
    return root
