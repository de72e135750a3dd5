"""One real team stack (PostgreSQL, SeaweedFS, MLflow with basic auth) on loopback for the tests of this
folder, on free ports, in a temp folder; stopped and deleted at the end. All run on one xdist worker
(group "team"), one after another in file order."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from pipeline.team.stack import Stack, free_base_port


@pytest.fixture(scope="session")
def team(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Stack]:
    stack = Stack(tmp_path_factory.mktemp("team") / "stack")
    stack.init(base_port=free_base_port())
    try:
        stack.start(progress=lambda _m: None)
        yield stack
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
