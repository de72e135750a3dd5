"""The team stack on one machine: its settings (`team.json`: ports and generated credentials), the
environment each role works with, and its four servers composed (`pipeline.team.servers`): PostgreSQL
(MLflow's backend and auth stores), SeaweedFS (`weed mini`, the S3 store behind MLflow's proxied
artifacts, the DVC remote and the bucket simulators fetch published champions from), an MLflow
tracking server with basic auth, and the publisher (`pipeline.team.publisher`: on every alias change,
MLflow's webhook has it publish the new version).

Everything lives in one state folder outside git (`$NEEDLECUE_TEAM_DIR`, default
`~/.local/state/needlecue/team`): `team.json` (mode 0600), the servers' data, logs and pid files, and
`<role>.env` files to source. Every server binds to `host` (127.0.0.1 unless told otherwise); the
ports are `base_port` + 0..8 (MLflow, S3, PostgreSQL, then SeaweedFS's internal ones, whose gRPC
ports are 10000 higher), and + 9 for the publisher's webhook listener.
"""

from __future__ import annotations

import base64
import contextlib
import json
import os
import secrets
import shutil
import socket
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pipeline.team import access
from pipeline.team.servers.base import Launch, Ports, Server, StackError, write_private
from pipeline.team.servers.mlflow import MLflow
from pipeline.team.servers.postgres import Postgres
from pipeline.team.servers.publisher import Publisher
from pipeline.team.servers.s3 import PUBLISHED, S3

FORMAT = "needlecue-team/1"
DIR_ENV = "NEEDLECUE_TEAM_DIR"
DEFAULT_DIR = "~/.local/state/needlecue/team"
DEFAULT_BASE_PORT = 5480
ROLES = ("admin", "lab", "simulator")
SERVERS = (Postgres.name, S3.name, MLflow.name, Publisher.name)  # in start order; stopped in reverse
# SeaweedFS marks every volume read-only once its disk has less than 1 % free (the volume server's
# -minFreeSpace default, which `weed mini` cannot change), after which every write fails with S3's bare
# "InternalError" and MLflow's artifact proxy answers 500 (seen in CI on a shared, nearly full disk).
S3_MIN_FREE_SHARE = 0.01
S3_HEADROOM = 2 * 1024**3  # closer than this to that line, `start` and `status` warn


@dataclass(frozen=True)
class DiskSpace:
    """Free space on the disk that holds SeaweedFS's data, against the line below which it writes nothing."""

    path: Path
    free: int
    total: int

    @property
    def floor(self) -> int:
        return int(self.total * S3_MIN_FREE_SHARE)

    @property
    def full(self) -> bool:
        return self.free < self.floor

    @property
    def low(self) -> bool:
        return self.free < self.floor + S3_HEADROOM

    def describe(self) -> str:
        gib = 1024**3
        said = f"{self.free / gib:.1f} GiB free on the disk of {self.path} ({self.total / gib:.0f} GiB)"
        share = f"{S3_MIN_FREE_SHARE * 100:g} % of the disk"
        line = f"SeaweedFS refuses every write below {self.floor / gib:.1f} GiB free ({share})"
        if self.full:
            return f"s3: {said}: {line}, so nothing can be stored; free some space"
        return f"s3: {said}; {line}" + (": close to it" if self.low else "")


def default_dir() -> Path:
    """`$NEEDLECUE_TEAM_DIR`, else `~/.local/state/needlecue/team` (read at call time)."""
    return Path(os.environ.get(DIR_ENV) or DEFAULT_DIR).expanduser()


def _token(n: int = 24) -> str:
    return secrets.token_urlsafe(n)


def new_settings(
    base_port: int = DEFAULT_BASE_PORT,
    host: str = "127.0.0.1",
    workers: int = 2,
    publish_every_s: float = 60.0,
) -> dict:
    """A new stack's settings: ports and freshly generated credentials."""
    if not 1024 <= base_port <= 65535 - 10008:
        raise ValueError(
            f"base_port {base_port}: needs 1024 .. {65535 - 10008} (gRPC ports are 10000 higher)"
        )
    return {
        "format": FORMAT,
        "host": host,
        "base_port": base_port,
        "workers": workers,
        "publish_every_s": publish_every_s,  # the publisher's round without a webhook call (a missed one)
        "passwords": {role: _token() for role in ROLES},
        "postgres_password": _token(),
        "s3": {"access_key": "needlecue" + secrets.token_hex(6), "secret_key": _token(30)},
        **publish_settings(),
        "flask_secret": _token(32),
        # Fernet key: MLflow encrypts the webhooks' signing secrets with it (one per process if unset)
        "webhook_encryption_key": base64.urlsafe_b64encode(os.urandom(32)).decode(),
        "webhook_secret": _token(),  # what MLflow signs alias webhooks with, and the simulators check
    }


def publish_settings() -> dict[str, Any]:
    """A simulator's read-only S3 keys and the lab's signing key (added to an older team.json on start)."""
    from needlecue_runtime.registry.manifest import new_private_key

    return {
        "s3_reader": {"access_key": "simulator" + secrets.token_hex(6), "secret_key": _token(30)},
        "publish_private_key": base64.b64encode(new_private_key()).decode(),
    }


class Stack:
    """One team stack, described by `<folder>/team.json` (created by `init`), and its servers."""

    def __init__(self, folder: Path | None = None) -> None:
        self.dir = (folder or default_dir()).expanduser().resolve()
        self.file = self.dir / "team.json"
        self.postgres, self.s3 = Postgres(self), S3(self)
        self.servers: dict[str, Server] = {
            s.name: s for s in (self.postgres, self.s3, MLflow(self), Publisher(self))
        }

    # --- settings and where things are -------------------------------------------------------------

    @property
    def settings(self) -> dict[str, Any]:
        try:
            found = json.loads(self.file.read_text())
        except FileNotFoundError:
            raise StackError(f"no team stack in {self.dir}: start one with `needlecue team start`") from None
        except (OSError, ValueError) as e:
            raise StackError(f"{self.file}: unreadable ({e})") from e
        if found.get("format") != FORMAT:
            raise StackError(f"{self.file}: format {found.get('format')!r}, this needlecue reads {FORMAT}")
        return found

    def init(
        self,
        base_port: int = DEFAULT_BASE_PORT,
        host: str = "127.0.0.1",
        workers: int = 2,
        publish_every_s: float = 60.0,
    ) -> bool:
        """Write team.json with new credentials unless it exists (then its settings stand): True if new."""
        if self.file.is_file():
            found = self.settings
            if "publish_private_key" not in found:  # a stack made before publishing: add its keys
                self._write({**found, **publish_settings()})
            return False
        self.dir.mkdir(parents=True, exist_ok=True)
        os.chmod(self.dir, 0o700)
        self._write(new_settings(base_port, host, workers, publish_every_s))
        return True

    def _write(self, settings: dict[str, Any]) -> None:
        write_private(self.file, json.dumps(settings, indent=2))

    @property
    def ports(self) -> Ports:
        return Ports(int(self.settings["base_port"]))

    @property
    def host(self) -> str:
        return str(self.settings["host"])

    @property
    def tracking_uri(self) -> str:
        return f"http://{self.host}:{self.ports.mlflow}"

    @property
    def s3_endpoint(self) -> str:
        return f"http://{self.host}:{self.ports.s3}"

    @property
    def published_url(self) -> str:
        """The published bucket, as a simulator's `NEEDLECUE_PUBLISHED_URL`."""
        return f"{self.s3_endpoint}/{PUBLISHED}"

    @property
    def publisher_url(self) -> str:
        """Where MLflow's webhook reaches the publisher."""
        return self.servers["publisher"].address

    def public_key(self) -> str:
        """The public half of the lab's publishing key (base64), as simulators hold it."""
        from needlecue_runtime.registry.manifest import public_of

        return base64.b64encode(public_of(base64.b64decode(self.settings["publish_private_key"]))).decode()

    def database_uri(self, database: str) -> str:
        """SQLAlchemy URI of one of the stack's databases."""
        return self.postgres.uri(database)

    @property
    def pg_dir(self) -> Path:
        """PostgreSQL's data folder."""
        return self.postgres.data_dir

    def log(self, server: str) -> Path:
        return self._server(server).log

    def s3_client(self) -> Any:
        """A boto3 client on the stack's S3 store (the lab's credentials)."""
        return self.s3.client()

    def as_lab(self) -> contextlib.AbstractContextManager[None]:
        """A block in which MLflow calls go to this stack's server as the lab (its tracking
        credentials in the environment, restored afterwards): how the stack's own tools read the
        registry."""
        from needlecue_runtime.registry import mlflow_env

        lab = self.role_env("lab")
        return mlflow_env.environment({k: v for k, v in lab.items() if k.startswith("MLFLOW_TRACKING_")})

    def role_env(self, role: str) -> dict[str, str]:
        """The environment a user of `role` works with: MLflow's URI and credentials, and for the lab
        and admin also the S3 store's (DVC's remote). A simulator gets the published bucket instead
        (read-only keys, the lab's public key): its client fetches from there, not from MLflow."""
        if role not in ROLES:
            raise ValueError(f"unknown role {role!r}: one of {', '.join(ROLES)}")
        s = self.settings
        env = {
            "MLFLOW_TRACKING_URI": self.tracking_uri,
            "MLFLOW_TRACKING_USERNAME": role,
            "MLFLOW_TRACKING_PASSWORD": s["passwords"][role],
        }
        keys = s["s3_reader"] if role == "simulator" else s["s3"]
        env |= {"AWS_ACCESS_KEY_ID": keys["access_key"], "AWS_SECRET_ACCESS_KEY": keys["secret_key"]}
        if role == "simulator":
            env |= {
                "NEEDLECUE_PUBLISHED_URL": self.published_url,
                "NEEDLECUE_PUBLISH_PUBLIC_KEY": self.public_key(),
            }
        env["NEEDLECUE_WEBHOOK_SECRET"] = s["webhook_secret"]
        return env

    def write_env_files(self) -> list[Path]:
        """`<role>.env` for each role (mode 0600): `set -a; . <file>; set +a` in a shell."""
        written = []
        for role in ROLES:
            path = self.dir / f"{role}.env"
            lines = [f"# needlecue team stack in {self.dir}: the {role} role\n"]
            lines += [f"{k}={v}\n" for k, v in self.role_env(role).items()]
            write_private(path, "".join(lines))
            written.append(path)
        return written

    # --- the servers ---------------------------------------------------------------------------------

    def _server(self, name: str) -> Server:
        try:
            return self.servers[name]
        except KeyError:
            raise ValueError(f"unknown server {name!r}: one of {', '.join(SERVERS)}") from None

    def launch(self, server: str) -> Launch:
        """The foreground command of `server` with this stack's settings (`Server.launch`)."""
        return self._server(server).launch()

    def start(self, progress: Any = print) -> None:
        """Start whatever of the servers is not running (each waited for until it answers), making
        sure the `lab` and `simulator` users exist with their permissions before the publisher."""
        space = self.disk_space()
        if space.full:
            raise StackError(space.describe())
        if space.low:
            progress(f"warning: {space.describe()}")
        for name, server in self.servers.items():
            if name == "publisher":  # it reads the registry as the lab, and has the admin add its webhook
                access.ensure_users(self)
            if server.running():
                progress(f"{name}: already running")
                continue
            server.check_ports_free()
            t0 = time.monotonic()
            server.start()
            progress(f"{name}: started in {time.monotonic() - t0:.1f} s ({server.log})")
        self.write_env_files()

    def running(self, server: str) -> bool:
        """Alive and answering on its port."""
        return self._server(server).running()

    def status(self) -> dict[str, dict[str, Any]]:
        """Each server: running or not, its pid, address and log."""
        return {
            name: {
                "running": server.running(),
                "pid": server.pid(),
                "address": server.address,
                "log": str(server.log),
            }
            for name, server in self.servers.items()
        }

    def disk_space(self) -> DiskSpace:
        """Free space where SeaweedFS keeps its data (the state folder)."""
        where = next(p for p in (self.dir, *self.dir.parents) if p.exists())
        usage = shutil.disk_usage(where)
        return DiskSpace(self.dir, usage.free, usage.total)

    def stop(self, purge: bool = False) -> list[str]:
        """Stop the servers (the publisher, MLflow, S3, then PostgreSQL); `purge` also deletes every byte
        the stack stored (its state folder and PostgreSQL's data). Returns the servers that were running."""
        stopped = [name for name in reversed(SERVERS) if self.servers[name].stop()]
        if purge:
            shutil.rmtree(self.pg_dir.parent, ignore_errors=True)
            shutil.rmtree(self.dir, ignore_errors=True)
        return stopped

    def stop_one(self, server: str, kill: bool = False) -> bool:
        """Stop one server (SIGKILL with `kill`, as a crash would); True if it was running."""
        return self._server(server).stop(kill)

    def start_one(self, server: str) -> None:
        """Start one server again (after `stop_one`)."""
        self._server(server).start()


def free_base_port(low: int = 20000, high: int = 29000) -> int:
    """A base port whose whole block (`Ports.all`) is free on loopback: for tests and benchmarks."""
    import random

    rng = random.Random()
    for _ in range(50):
        base = rng.randrange(low, high, 10)
        if all(_bindable(port) for port in Ports(base).all()):
            return base
    raise StackError(f"no free block of ports between {low} and {high}")


def _bindable(port: int) -> bool:
    with socket.socket() as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True
