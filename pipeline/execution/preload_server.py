"""The preload server (`pipeline.execution.preload` says why and how): started by a caller as
`python -m pipeline.execution.preload_server SOCKET`, it detaches, imports the heavy libraries once and
forks a supervisor per caller, which forks the stage process, made what a fresh `python -m` would be."""

from __future__ import annotations

import contextlib
import fcntl
import gc
import json
import os
import runpy
import select
import signal
import socket
import struct
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pipeline.execution.preload import REFUSED, identity, identity_differences

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

MODULES_ENV = "NEEDLECUE_PRELOAD_MODULES"  # comma-separated, instead of PRELOAD (the tests' servers)
ALLOWED_THREADS = frozenset({"jemalloc_bg_thd"})  # Arrow's allocator; its fork handlers reset it
IDLE_S = 90.0  # a server with no stage for this long exits (the gaps of a `dvc repro` are seconds)


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
    # not its caller's rights: a fresh interpreter
    if differs := identity_differences(identity(), identity(peer)):
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
