"""What every server of the team stack is: a process this machine starts, waits for until it
answers, finds again by its pid and stops (`Server`), seen through what it reads of its stack
(`StackView`), and the stack's port layout (`Ports`).

A server spawned here runs in its own session, its output appended to its log and its pid in
`run/<name>.pid` under the stack's folder; it is running when that process is alive and its port
answers. Subclasses say how to launch it (`launch`) and when it is ready (`ready`).
"""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, Protocol

START_TIMEOUT_S = 120.0
STOP_TIMEOUT_S = 30.0


class StackError(RuntimeError):
    """A server of the stack could not be started or stopped (the message says which and where its log is)."""


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


class StackView(Protocol):
    """What a server reads of its stack (`pipeline.team.stack.Stack` is one)."""

    dir: Path

    @property
    def settings(self) -> dict[str, Any]: ...
    @property
    def host(self) -> str: ...
    @property
    def ports(self) -> Ports: ...
    @property
    def tracking_uri(self) -> str: ...
    @property
    def s3_endpoint(self) -> str: ...
    def database_uri(self, database: str) -> str: ...


class Server:
    """One server of the stack: start it (spawned, then waited for until `ready`), tell whether it
    runs, stop it. A subclass gives its `name` (its port's in `Ports`), `launch`, and where they
    differ from these, the ports it binds, its `address` and `ready`."""

    name: ClassVar[str]

    def __init__(self, stack: StackView) -> None:
        self.stack = stack

    # --- what a subclass says -----------------------------------------------------------------------

    @property
    def port(self) -> int:
        """The port it answers on: the stack's port of its name (`Ports`)."""
        return int(getattr(self.stack.ports, self.name))

    @property
    def address(self) -> str:
        """Where a user reaches it."""
        return f"{self.stack.host}:{self.port}"

    def binds(self) -> list[int]:
        """Every port it binds (checked free before it starts)."""
        return [self.port]

    def launch(self) -> Launch:
        """Its foreground command with the stack's settings (writing the config files it reads)."""
        raise NotImplementedError

    def ready(self) -> bool:
        """Whether it serves requests yet."""
        return answers(self.stack.host, self.port)

    # --- the lifecycle ------------------------------------------------------------------------------

    @property
    def log(self) -> Path:
        return self.stack.dir / "logs" / f"{self.name}.log"

    @property
    def pid_file(self) -> Path:
        return self.stack.dir / "run" / f"{self.name}.pid"

    def check_ports_free(self) -> None:
        busy = [port for port in self.binds() if answers(self.stack.host, port)]
        if busy:
            raise StackError(f"{self.name}: port(s) {busy} on {self.stack.host} are taken by another program")

    def start(self) -> None:
        """Spawn it and wait until it is `ready`."""
        launch = self.launch()
        self.log.parent.mkdir(parents=True, exist_ok=True)
        self.pid_file.parent.mkdir(parents=True, exist_ok=True)
        with open(self.log, "ab") as out:
            proc = subprocess.Popen(
                launch.cmd, cwd=launch.cwd, env={**os.environ, **launch.env}, stdout=out,
                stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, start_new_session=True,
            )  # fmt: skip
        self.pid_file.write_text(f"{proc.pid}\n")
        self.wait()

    def wait(self, timeout: float = START_TIMEOUT_S) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.ready():
                return
            if self.pid() is None:
                raise StackError(f"{self.name}: exited while starting; its log: {self.log}\n{tail(self.log)}")
            time.sleep(0.3)
        raise StackError(f"{self.name}: not answering after {timeout:.0f} s; its log: {self.log}")

    def recorded_pid(self) -> int | None:
        """The pid it was started with, as recorded."""
        try:
            return int(self.pid_file.read_text())
        except (OSError, ValueError):
            return None

    def pid(self) -> int | None:
        """The pid of the process started, if it is still alive."""
        pid = self.recorded_pid()
        if pid is None:
            return None
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return None
        except PermissionError:
            pass
        return None if _is_zombie(pid) else pid

    def running(self) -> bool:
        """Alive and answering on its port."""
        return self.pid() is not None and answers(self.stack.host, self.port)

    def stop(self, kill: bool = False) -> bool:
        """Stop it (SIGKILL with `kill`, as a crash would); True if it was running."""
        pid = self.pid()
        if pid is None:
            return False
        self._signal(pid, signal.SIGKILL if kill else signal.SIGTERM)
        deadline = time.monotonic() + STOP_TIMEOUT_S
        while self.pid() is not None and time.monotonic() < deadline:
            time.sleep(0.1)
        if self.pid() is not None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(pid, signal.SIGKILL)
        with contextlib.suppress(ChildProcessError):
            os.waitpid(pid, os.WNOHANG)
        return True

    def _signal(self, pid: int, sig: int) -> None:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(pid, sig)


def answers(host: str, port: int) -> bool:
    """Whether something accepts a connection on host:port."""
    with socket.socket() as s:
        s.settimeout(0.5)
        return s.connect_ex((host, port)) == 0


def write_private(path: Path, text: str) -> None:
    """Write a file only its owner reads (mode 0600) by a rename: a server reading it meanwhile (the
    config `team units` writes again) sees the old file or the new one, never half of it."""
    tmp = path.with_name(f".{path.name}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(text)
    tmp.replace(path)


def run(cmd: list[str], what: str) -> None:
    """Run a command to its end; StackError naming `what` with its output if it fails."""
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=120, stdin=subprocess.DEVNULL)
    if done.returncode != 0:
        raise StackError(f"{what} failed (exit {done.returncode}):\n{done.stdout}{done.stderr}".rstrip())


def tail(path: Path, n: int = 15) -> str:
    try:
        return "\n".join(path.read_text(errors="replace").splitlines()[-n:])
    except OSError:
        return ""


def _is_zombie(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().split(") ", 1)[1].startswith("Z")
    except (OSError, IndexError):
        return False
