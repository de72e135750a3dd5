"""The MLflow tracking server with basic auth: its backend and auth stores in PostgreSQL, its
artifacts proxied to the S3 store, workspaces on, alias webhooks allowed to the lab's network."""

from __future__ import annotations

import sys
import urllib.error
import urllib.request
from pathlib import Path

from pipeline.registry.ui import SERVER_ENV
from pipeline.team.servers.base import Launch, Server, write_private

# uvicorn kills a worker that leaves its health ping unanswered for 5 s (its default), and a worker busy
# on a loaded machine can: the kill drops every request it holds, a register's upload among them (seen
# with the pipeline and the tests sharing 2 cores). A hung worker is still replaced, after a minute.
WORKER_HEALTHCHECK_S = 60


class MLflow(Server):
    name = "mlflow"

    @property
    def address(self) -> str:
        return self.stack.tracking_uri

    def env(self) -> dict[str, str]:
        """Its environment: where the artifacts go, the auth config, the secrets."""
        s = self.stack.settings
        return {
            **SERVER_ENV,
            "MLFLOW_BACKEND_STORE_URI": self.stack.database_uri("mlflow"),  # in the environment: not in `ps`
            "MLFLOW_S3_ENDPOINT_URL": self.stack.s3_endpoint,
            "AWS_ACCESS_KEY_ID": s["s3"]["access_key"],
            "AWS_SECRET_ACCESS_KEY": s["s3"]["secret_key"],
            "AWS_DEFAULT_REGION": "us-east-1",
            "MLFLOW_AUTH_CONFIG_PATH": str(self._auth_config()),
            "MLFLOW_FLASK_SERVER_SECRET_KEY": s["flask_secret"],
            "MLFLOW_WEBHOOK_SECRET_ENCRYPTION_KEY": s["webhook_encryption_key"],
            # the simulators a webhook calls sit on the lab's own (private) network
            "MLFLOW_WEBHOOK_ALLOW_PRIVATE_IPS": "true",
            # their listeners speak plain HTTP on it (the body is signed; it carries no secret)
            "MLFLOW_WEBHOOK_ALLOWED_SCHEMES": "http,https",
            "MLFLOW_WEBHOOK_REQUEST_MAX_RETRIES": "1",
            "MLFLOW_WEBHOOK_REQUEST_TIMEOUT": "5",
            "MLFLOW_WEBHOOK_CACHE_TTL": "10",  # a new webhook is called within 10 s (MLflow: 60)
        }

    def _auth_config(self) -> Path:
        """basic_auth.ini: users and permissions in PostgreSQL; nobody reads without a user; the admin's
        password is set before the first start (MLflow ships none)."""
        s = self.stack.settings
        path = self.stack.dir / "basic_auth.ini"
        text = (
            "[mlflow]\n"
            "default_permission = NO_PERMISSIONS\n"
            f"database_uri = {self.stack.database_uri('mlflow_auth')}\n"
            "admin_username = admin\n"
            f"admin_password = {s['passwords']['admin']}\n"
            "authorization_function = mlflow.server.auth:authenticate_request_basic_auth\n"
            # Checking a password (PBKDF2) costs more CPU than most requests; a run is hundreds of
            # requests. Cached per worker for a minute: a changed password or role applies within it.
            "auth_cache_ttl_seconds = 60\n"
        )
        write_private(path, text)
        return path

    def launch(self) -> Launch:
        cmd = [
            sys.executable, "-m", "mlflow", "server", "--app-name", "basic-auth",
            "--serve-artifacts", "--artifacts-destination", "s3://mlflow/artifacts",
            # workspaces on: without them every signed-in user may create experiments and models
            "--enable-workspaces",
            "--host", self.stack.host, "--port", str(self.port),
            "--workers", str(self.stack.settings["workers"]),
            "--uvicorn-opts", f"--timeout-worker-healthcheck {WORKER_HEALTHCHECK_S}",
        ]  # fmt: skip
        return Launch(cmd, self.env(), self.stack.dir)

    def ready(self) -> bool:
        """Its /health answers 200."""
        try:
            with urllib.request.urlopen(f"{self.stack.tracking_uri}/health", timeout=2) as r:
                return r.status == 200
        except (OSError, urllib.error.URLError):
            return False
