"""Stages in a warm interpreter: a local server that has imported the heavy libraries once forks a
process for each stage, so that a stage starts in a fraction of a second instead of importing torch,
pandas, scipy, Great Expectations and MLflow afresh (6 to 20 s of CPU on the project's 2-core
machines, for about 30 stages of a cold run).

`pipeline.execution.run` asks the server (`run_stage`) and falls back to starting the stage itself
when there is none yet, starting one for the next stage. The stage process is the server's fork,
given what a fresh one would have: the caller's stdin, stdout and stderr (passed over the socket),
working directory, environment, CPU affinity and arguments, the project's own code imported afresh
from its folder, and the default signal handlers; the caller waits for it, forwards Ctrl-C and exits
with its status, and a stage whose caller dies is killed at once.

A stage runs as its caller: the server serves only a caller with its own identity (user and group
ids, groups, capabilities, no-new-privileges, seccomp, umask and resource limits, `identity`). That
identity is part of the key, so a caller who has given something up finds its own server, and the
server checks each caller's (the socket's peer) before forking; a caller it refuses runs the stage
in a fresh interpreter. Results are the same bytes either way: the server runs with the
pinned environment of the stages it serves (part of its key, as is everything a library could read
when it loads), has run no numeric code, and started no thread but the allocator's.

One server per user, Python and environment key, in a private folder (`socket_dir`; its log beside
the socket); it exits after `IDLE_S` without a stage. `NEEDLECUE_PRELOAD=0` turns it off (every
stage a fresh interpreter).
"""

from __future__ import annotations

import contextlib
import fcntl
import gc
import hashlib
import json
import os
import runpy
import select
import signal
import site
import socket
import struct
import subprocess
import sys
import tempfile
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

# what the stages import that takes long to load; no module that starts a thread when imported
# (onnxruntime does: a fork must not copy a thread mid-use), none of the project's own
PRELOAD = (
    "numpy",
    "pandas",
    "pyarrow.parquet",
    "scipy.linalg",
    "scipy.signal",
    "torch",
    "typer",
    "pydantic",
    "yaml",
    "matplotlib",
    "sklearn.covariance",
    "mlflow",
    "great_expectations",
)
IDLE_S = 90.0  # a server with no stage for this long exits (the gaps of a `dvc repro` are seconds)
PROTOCOL = "needlecue-preload/2"
REFUSED = "refused"  # the server's answer to a caller whose identity is not its own
OFF = "NEEDLECUE_PRELOAD"  # "0": no server, every stage a fresh interpreter
MODULES_ENV = "NEEDLECUE_PRELOAD_MODULES"  # comma-separated, instead of PRELOAD (the tests' servers)
DIR_ENV = "NEEDLECUE_PRELOAD_DIR"  # where the sockets live (default: a private folder in the temp dir)
# read by the stages when they run, never by a library as it loads: they may differ between the
# callers of one server (each stage gets the caller's whole environment)
RUNTIME_PREFIXES = ("MLFLOW_", "AWS_", "PYTEST_", "DVC_", "GIT_", "NEEDLECUE_")
RUNTIME_NAMES = frozenset({"PWD", "OLDPWD", "SHLVL", "_", "COLUMNS", "LINES"})
MAX_LOG_BYTES = 1 << 20  # a server's log (a line per stage) starts over past this
MAX_SOCKET_PATH = 100  # bytes: Linux takes 107 (macOS 103) in a Unix socket's address
ALLOWED_THREADS = frozenset({"jemalloc_bg_thd"})  # Arrow's allocator; its fork handlers reset it


def enabled(env: Mapping[str, str]) -> bool:
    return env.get(OFF, "1") != "0" and hasattr(os, "fork") and hasattr(socket, "send_fds")


IDENTITY_FIELDS = ("Uid", "Gid", "Groups", "CapInh", "CapPrm", "CapEff", "CapBnd", "CapAmb", "NoNewPrivs")
IDENTITY_FIELDS += ("Seccomp", "Umask")  # /proc/<pid>/status lines that say what a process may do


def identity(pid: int | str = "self") -> dict[str, str]:
    """What process `pid` may do, from /proc (Linux): its ids, groups, capabilities, no-new-privileges,
    seccomp mode, umask and resource limits. {} where /proc cannot say (then no server serves)."""
    folder = Path("/proc") / str(pid)
    try:
        status, limits = (folder / "status").read_text(), (folder / "limits").read_text()
    except OSError:
        return {}
    out = {}
    for line in status.splitlines():
        name, _, value = line.partition(":")
        if name in IDENTITY_FIELDS:
            words = value.split()
            out[name] = " ".join(sorted(words) if name == "Groups" else words)
    out["limits"] = "\n".join(" ".join(line.split()) for line in limits.splitlines())
    return out


def _differs(mine: Mapping[str, str], theirs: Mapping[str, str]) -> list[str]:
    """The identity fields that differ (all of them when either is unknown)."""
    if not mine or not theirs:
        return ["unknown identity"]
    return sorted(k for k in set(mine) | set(theirs) if mine.get(k) != theirs.get(k))


def key(env: Mapping[str, str]) -> str:
    """What a server must share with its callers: this Python and its installed packages, the code of
    this module, every environment variable a library could read as it loads, and the caller's
    identity (a stage runs as its caller)."""
    loading = {k: v for k, v in env.items() if k not in RUNTIME_NAMES and not k.startswith(RUNTIME_PREFIXES)}
    # an install or upgrade changes its site-packages folder: a new server, never a stale library
    installed = [os.stat(p).st_mtime_ns for p in site.getsitepackages() if os.path.isdir(p)]
    code = Path(__file__).read_text()
    doc = [PROTOCOL, sys.executable, sys.version, installed, code, sorted(loading.items()), identity()]
    return hashlib.sha256(json.dumps(doc).encode()).hexdigest()[:32]


def socket_path(env: Mapping[str, str]) -> Path | None:
    """The server's socket for callers with `env`; None where a socket cannot be (a path longer than
    Unix sockets take, a folder that is not private)."""
    try:
        path = socket_dir(env) / f"{key(env)}.sock"
    except OSError:
        return None
    return path if len(os.fsencode(path)) <= MAX_SOCKET_PATH else None


def socket_dir(env: Mapping[str, str]) -> Path:
    """A folder only this user can enter (created if need be; refused if someone else could)."""
    folder = Path(env.get(DIR_ENV) or Path(tempfile.gettempdir()) / f"needlecue-preload-{os.getuid()}")
    folder.mkdir(mode=0o700, parents=True, exist_ok=True)
    info = folder.stat()
    if info.st_uid != os.getuid() or info.st_mode & 0o077:
        raise PermissionError(f"{folder}: not a private folder of this user")
    return folder


# -- the caller --------------------------------------------------------------------------------


def run_stage(argv: list[str], env: Mapping[str, str]) -> int | None:
    """Run `python -m` `argv` (module, args...) in a warm process: its exit status (128 + the signal
    that ended it), or None when no server could take it (the caller starts the stage itself; a
    server is being started for the next one)."""
    if not enabled(env) or (path := socket_path(env)) is None:
        return None
    status = ask(path, argv, env)
    if status == REFUSED:
        return None  # a server of this key that does not serve this caller: a fresh interpreter
    if status is None:
        _start_server(path, env)
    return status


def ask(path: Path, argv: list[str], env: Mapping[str, str]) -> int | str | None:
    """The stage run by the server at `path`: its exit status, REFUSED (the server does not serve
    this caller), or None (no server there, or it went away before starting the stage)."""
    conn = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        conn.connect(str(path))
        request = {"argv": argv, "cwd": os.getcwd(), "env": dict(env), "cpus": _cpus()}
        payload = json.dumps(request).encode()
        socket.send_fds(conn, [struct.pack("!I", len(payload)) + payload], [0, 1, 2])
        answer = _read_line(conn)
        if answer.startswith(REFUSED):
            conn.close()
            return REFUSED
        pid = int(answer.removeprefix("pid "))
    except (OSError, ValueError):
        conn.close()
        return None
    return _wait(conn, pid)


def _cpus() -> list[int]:
    affinity = getattr(os, "sched_getaffinity", None)
    return sorted(affinity(0)) if affinity else []


def _read_line(conn: socket.socket) -> str:
    data = b""
    while not data.endswith(b"\n"):
        chunk = conn.recv(64)
        if not chunk:
            raise ConnectionError("the preload server closed the connection")
        data += chunk
    return data.decode().strip()


def _wait(conn: socket.socket, pid: int) -> int:
    """Wait for the stage process, forwarding the signals that would have reached it; its status."""

    def forward(signum: int, _frame: Any) -> None:
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signum)

    for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP, signal.SIGQUIT):
        signal.signal(s, forward)
    try:
        status = _read_line(conn)
    except (OSError, ConnectionError) as e:
        print(f"pipeline.execution.run: lost the stage process {pid}: {e}", file=sys.stderr)
        return 1
    kind, _, value = status.partition(" ")
    return int(value) if kind == "exit" else 128 + int(value)


def _start_server(path: Path, env: Mapping[str, str]) -> None:
    """Start a server for `path` in the background (it detaches itself at once); never fails."""
    cmd = [sys.executable, "-m", "pipeline.execution.preload", str(path)]
    with contextlib.suppress(OSError, subprocess.SubprocessError):
        log_path = path.with_suffix(".log")
        big = log_path.is_file() and log_path.stat().st_size > MAX_LOG_BYTES
        log = open(log_path, "wb" if big else "ab")  # noqa: SIM115 (the server keeps it)
        with log:
            subprocess.run(cmd, env=dict(env), stdin=subprocess.DEVNULL, stdout=log, stderr=log, timeout=30)


# -- the server --------------------------------------------------------------------------------


@dataclass
class _Stage:
    """What the forked stage process runs: a fresh interpreter's `python -m module args`."""

    argv: list[str]
    cwd: str

    def run(self) -> None:
        for name in [m for m in sys.modules if m == "pipeline" or m.startswith("pipeline.")]:
            del sys.modules[name]  # the project's code: from the stage's folder, as a fresh process would
        sys.path[0] = self.cwd
        import importlib

        importlib.invalidate_caches()
        runpy.run_module(self.argv[0], run_name="__main__", alter_sys=True)


def _detach() -> None:
    """Leave the caller: double fork, a new session, nothing of the caller's held open."""
    if os.fork():
        os._exit(0)
    os.setsid()
    if os.fork():
        os._exit(0)


def _other_threads() -> list[str]:
    """The names of this process's threads but the main one (Linux; none known elsewhere)."""
    folder = Path("/proc/self/task")
    if not folder.is_dir():
        return []
    return [(t / "comm").read_text().strip() for t in folder.iterdir() if t.name != str(os.getpid())]


def serve(path: Path) -> _Stage | None:
    """Preload, then fork a supervisor per connection until idle; returns only in a stage process."""
    lock = open(path.with_suffix(".lock"), "w")  # noqa: SIM115 (held for the server's life)
    try:
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        return None  # another server has this key
    path.unlink(missing_ok=True)  # a dead server's
    server = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    server.bind(str(path))  # before the imports: a path that cannot be bound fails at once
    started = time.perf_counter()
    listed = os.environ.get(MODULES_ENV)
    for module in PRELOAD if listed is None else [m for m in listed.split(",") if m]:
        try:
            __import__(module)
        except Exception as e:  # a library that cannot load is just not preloaded
            print(f"preload: {module} not preloaded: {e}", flush=True)
    extra = [t for t in _other_threads() if t not in ALLOWED_THREADS]
    if extra:
        print(f"preload: threads {extra} after the imports: not serving (a fork would copy them)", flush=True)
        path.unlink(missing_ok=True)
        return None
    # what the imports made is never collected again: a collection in a stage process would otherwise
    # touch every object of the libraries, copying the server's memory page by page (seconds a stage)
    gc.collect()
    gc.freeze()
    server.listen(64)  # callers find it from now on (before, their connect is refused: they fall back)
    server.settimeout(IDLE_S)
    mine = path.stat().st_ino
    print(f"preload: ready in {time.perf_counter() - started:.1f} s, pid {os.getpid()}, {path}", flush=True)
    signal.signal(signal.SIGCHLD, signal.SIG_IGN)  # supervisors are reaped as they end
    while True:
        try:
            conn, _ = server.accept()
        except TimeoutError:
            with contextlib.suppress(OSError):
                if path.stat().st_ino == mine:
                    path.unlink()
            return None
        if os.fork() == 0:
            server.close()
            lock.close()
            signal.signal(signal.SIGCHLD, signal.SIG_DFL)
            return _supervise(conn)
        conn.close()


def _supervise(conn: socket.socket) -> _Stage | None:
    """One stage: receive the request and the caller's stdio, fork the stage process, report its pid
    and then its exit status; stop it if the caller goes away. Returns only in the stage process."""
    try:
        data, fds, _, _ = socket.recv_fds(conn, 1 << 16, 3)
        if len(data) < 4 or len(fds) != 3:
            os._exit(2)
        size = struct.unpack("!I", data[:4])[0]
        body = data[4:]
        while len(body) < size:
            chunk = conn.recv(size - len(body))
            if not chunk:
                os._exit(2)
            body += chunk
        request = json.loads(body)
    except (OSError, ValueError):
        os._exit(2)
    cred = struct.calcsize("3i")
    peer, _uid, _gid = struct.unpack("3i", conn.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, cred))
    if differs := _differs(identity(), identity(peer)):  # not its caller's rights: a fresh interpreter
        for fd in fds:
            os.close(fd)
        print(
            f"preload: refused caller {peer}: its {', '.join(differs)} differ from the server's", flush=True
        )
        # the whole request was read first and the caller closes after reading the answer: an answer
        # sent to a caller still writing, or a close with its data unread, would reach it as a broken
        # connection (no server) instead of a refusal
        with contextlib.suppress(OSError):
            conn.sendall(f"{REFUSED} {', '.join(differs)}\n".encode())
            conn.settimeout(5.0)
            while conn.recv(64):
                pass
        os._exit(0)
    pid = os.fork()
    if pid == 0:
        conn.close()
        return _become_stage(request, fds)
    for fd in fds:
        os.close(fd)
    print(f"preload: stage {pid}: {' '.join(request['argv'])} in {request['cwd']}", flush=True)
    conn.sendall(f"pid {pid}\n".encode())
    waiter = os.pidfd_open(pid) if hasattr(os, "pidfd_open") else None
    while True:
        ready, _, _ = select.select([conn, *([waiter] if waiter is not None else [])], [], [], 0.05)
        done, status = os.waitpid(pid, os.WNOHANG)
        if done:
            code = os.waitstatus_to_exitcode(status)
            reply = f"exit {code}" if code >= 0 else f"signal {-code}"
            with contextlib.suppress(OSError):
                conn.sendall(f"{reply}\n".encode())
            os._exit(0)
        if conn in ready and not conn.recv(1, socket.MSG_PEEK):
            # the caller is gone, killed outright (its signals are forwarded): so is its stage, at once,
            # as a fresh interpreter (the caller's own process) would be
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
            os._exit(0)


def _become_stage(request: dict[str, Any], fds: list[int]) -> _Stage:
    """Turn this fork into what a fresh `python -m` of the request would be, up to running it."""
    for fd, target in zip(fds, (0, 1, 2), strict=True):
        os.dup2(fd, target)
        os.close(fd)
    for s in (signal.SIGTERM, signal.SIGHUP, signal.SIGQUIT, signal.SIGCHLD):
        signal.signal(s, signal.SIG_DFL)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    os.chdir(request["cwd"])
    os.environ.clear()
    os.environ.update(request["env"])
    if request["cpus"] and hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, request["cpus"])
    line = os.environ.get("PYTHONUNBUFFERED", "") == "" and os.isatty(1)
    sys.stdin = open(0, closefd=False)  # noqa: SIM115
    sys.stdout = open(1, "w", buffering=1 if line else -1, encoding="utf-8", closefd=False)  # noqa: SIM115
    sys.stderr = open(2, "w", buffering=1, encoding="utf-8", errors="backslashreplace", closefd=False)  # noqa: SIM115
    sys.argv = list(request["argv"])
    return _Stage(list(request["argv"]), request["cwd"])


def main(argv: list[str]) -> None:
    path = Path(argv[0])
    _detach()
    os.chdir("/")  # hold no folder of the caller's
    stage = serve(path)
    if stage is None:
        os._exit(0)
    stage.run()  # a stage process: exits as `python -m` would, atexit handlers and all


if __name__ == "__main__":
    main(sys.argv[1:])
