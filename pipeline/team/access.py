"""Who may do what on the team's MLflow server (basic auth, workspaces on): three roles.

- `admin`: MLflow's own administrator (users, roles, webhooks).
- `lab`: creates experiments, runs and registered models, registers versions and moves aliases
  (`dvc repro`'s register stage, `needlecue rollback`, `retrain`, `calibrate`).
- `simulator`: reads experiments and registered models (fetches champions and unit calibrations),
  nothing else: no run, no alias, no new experiment or model.

Anonymous requests are refused (`default_permission = NO_PERMISSIONS`). A role is a set of MLflow RBAC
grants on every resource (`*`) of the `default` workspace, so a model registered tomorrow is covered.
"""

from __future__ import annotations

import contextlib
import secrets
from collections.abc import Iterator
from typing import Any, Protocol

from needlecue_runtime.registry.mlflow_env import environment


class Server(Protocol):
    """What granting access needs of a team's MLflow server (`pipeline.team.stack.Stack` is one)."""

    @property
    def tracking_uri(self) -> str: ...

    @property
    def settings(self) -> dict[str, Any]: ...  # "passwords" per role, "webhook_secret"

    def role_env(self, role: str) -> dict[str, str]: ...  # MLFLOW_TRACKING_USERNAME/_PASSWORD


WORKSPACE = "default"
GRANTS: dict[str, list[tuple[str, str]]] = {
    "lab": [("workspace", "USE"), ("experiment", "MANAGE"), ("registered_model", "MANAGE")],
    "simulator": [("experiment", "READ"), ("registered_model", "READ")],
}
DESCRIPTIONS = {
    "lab": "registers models and moves aliases",
    "simulator": "reads champions and unit calibrations, nothing else",
}
ALIAS_EVENTS = ["model_version_alias.created", "model_version_alias.deleted"]


@contextlib.contextmanager
def _as_admin(stack: Server) -> Iterator[Any]:
    """MLflow's auth client, with the admin's credentials in the environment while it is used (the
    client reads them from there)."""
    from mlflow.server import get_app_client

    env = stack.role_env("admin")
    with environment({k: env[k] for k in ("MLFLOW_TRACKING_USERNAME", "MLFLOW_TRACKING_PASSWORD")}):
        yield get_app_client("basic-auth", tracking_uri=stack.tracking_uri)


def _exists(call: Any) -> bool:
    from mlflow.exceptions import MlflowException

    try:
        call()
    except MlflowException as e:
        if e.error_code == "RESOURCE_DOES_NOT_EXIST":
            return False
        raise
    return True


def ensure_roles(auth: Any) -> dict[str, Any]:
    """The `lab` and `simulator` roles with their grants (created once; grants added if missing)."""
    roles = {r.name: r for r in auth.list_roles(WORKSPACE)}
    for name, grants in GRANTS.items():
        if name not in roles:
            roles[name] = auth.create_role(WORKSPACE, name, DESCRIPTIONS[name])
        have = {(p.resource_type, p.permission) for p in auth.list_role_permissions(roles[name].id)}
        for resource, permission in grants:
            if (resource, permission) not in have:
                auth.add_role_permission(roles[name].id, resource, "*", permission)
    return roles


def add_user(stack: Server, username: str, role: str, password: str | None = None) -> str:
    """Create `username` with `role` (`lab` or `simulator`); returns the password (generated unless
    given). A user that exists keeps its password and gets the role."""
    if role not in GRANTS:
        raise ValueError(f"role {role!r}: a user is one of {', '.join(GRANTS)} (admin is MLflow's own)")
    password = password or secrets.token_urlsafe(24)
    with _as_admin(stack) as auth:
        roles = ensure_roles(auth)
        if not _exists(lambda: auth.get_user(username)):
            auth.create_user(username, password)
        if role not in {r.name for r in auth.list_user_roles(username)}:
            auth.assign_role(username, roles[role].id)
    return password


def ensure_users(stack: Server) -> None:
    """The stack's own `lab` and `simulator` users, with the passwords in its team.json."""
    passwords = stack.settings["passwords"]
    for role in GRANTS:
        add_user(stack, role, role, passwords[role])


def add_webhook(stack: Server, url: str, name: str = "needlecue-alias") -> str:
    """Have the server call `url` (a simulator's listener, `needlecue_client.webhook`) on every alias
    change, signed with the stack's webhook secret; returns the webhook's id. Needs the admin."""
    from mlflow import MlflowClient

    with _as_admin(stack):
        client = MlflowClient(tracking_uri=stack.tracking_uri)
        hook = client.create_webhook(
            name=name, url=url, events=list(ALIAS_EVENTS), secret=stack.settings["webhook_secret"]
        )
    return str(hook.webhook_id)


def ensure_webhook(stack: Server, url: str, name: str) -> str:
    """The webhook `name` calling `url` on every alias change (created, or its URL updated); its id."""
    from mlflow import MlflowClient

    with _as_admin(stack):
        client = MlflowClient(tracking_uri=stack.tracking_uri)
        for hook in client.list_webhooks(max_results=1000):
            if hook.name == name:
                if hook.url != url:
                    client.update_webhook(hook.webhook_id, url=url)
                return str(hook.webhook_id)
    return add_webhook(stack, url, name)
