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
from typing import Any, NoReturn

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
    "torch._dynamo",  # torch.optim loads it at an optimizer's first step: 1.3 s of each calibrate
    "torch.onnx",
    "typer",
    "pydantic",
    "yaml",
    "matplotlib",
    "matplotlib.pyplot",
    "sklearn.covariance",
    "mlflow",
    "mlflow.store.tracking.sqlalchemy_store",
    "great_expectations",
)

MODULES_ENV = "NEEDLECUE_PRELOAD_MODULES"  # comma-separated, instead of PRELOAD (the tests' servers)
ALLOWED_THREADS = frozenset({"jemalloc_bg_thd"})  # Arrow's allocator; its fork handlers reset it
IDLE_S = 90.0  # a server with no stage for this long exits (the gaps of a `dvc repro` are seconds)


# the project's own packages: never preloaded, always imported afresh by the stage (from its folder and
# its import path, as a fresh process would)
PROJECT = ("pipeline", "needlecue_runtime", "needlecue_client")


@dataclass
class _Stage:
    """What the forked stage process runs: a fresh interpreter's `python -m module args`."""

    argv: list[str]
    path: list[str]

    def run(self) -> NoReturn:
        for name in [m for m in sys.modules if m.partition(".")[0] in PROJECT]:
            del sys.modules[name]
        sys.path[:] = self.path
        import importlib

        importlib.invalidate_caches()
        try:
            runpy.run_module(self.argv[0], run_name="__main__", alter_sys=True)
        except SystemExit as e:
            _exit(_exit_status(e.code))
        _exit(0)  # an uncaught exception takes the interpreter's own way out: its traceback, status 1


def _exit_status(code: object) -> int:
    """The status `sys.exit(code)` gives: 0 for None, the number, else 1 with the message on stderr."""
    if code is None:
        return 0
    if isinstance(code, int):
        return code
    print(code, file=sys.stderr)
    return 1


def _exit(status: int) -> NoReturn:
    """End the stage as the interpreter would, as far as anyone can see: wait for its threads (and run
    their exit hooks: a process pool's shutdown), run the atexit handlers (logging's flush, MLflow's end
    of run), collect garbage (closing what a cycle holds open) and flush stdout and stderr. Then leave
    without tearing down every module: in a fork of the server that touches, and so copies, most of
    the server's memory, 0.4 s a stage."""
    import atexit
    import threading

    threading._shutdown()  # type: ignore[attr-defined]  # what Py_FinalizeEx calls first
    atexit._run_exitfuncs()
    gc.collect()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    os._exit(status)


def _detach() -> None:
    """Leave the caller: double fork, a new session, nothing of the caller's held open."""
    if os.fork():
        os._exit(0)
    os.setsid()
    if os.fork():
        os._exit(0)


def stage_path(request: dict[str, Any]) -> list[str]:
    """The import path of a fresh `python -m` of the request: the one the caller sent, else this
    server's (the key then holds the PYTHONPATH) with the caller's folder first."""
    return request.get("path") or [request["cwd"], *sys.path[1:]]


def found(names: list[str], path: list[str]) -> dict[str, Any]:
    """Where `path` finds each top-level module of `names` (None: not on it, as for a built-in)."""
    from importlib.machinery import PathFinder

    out: dict[str, Any] = {}
    for name in names:
        spec = PathFinder.find_spec(name, path)
        out[name] = None if spec is None else [spec.origin, list(spec.submodule_search_locations or ())]
    return out


def elsewhere(loaded: dict[str, Any], path: list[str]) -> list[str]:
    """The loaded libraries (`found` on the server's path) that `path` would find somewhere else."""
    theirs = found(list(loaded), path)
    return sorted(name for name, where in loaded.items() if theirs[name] != where)


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
    # where this server found what it loaded: a caller's path must find the same (`_supervise`)
    names = sorted({m.partition(".")[0] for m in sys.modules} - {"__main__", *PROJECT})
    loaded = found(names, sys.path)
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
            return _supervise(conn, loaded)
        conn.close()


def _supervise(conn: socket.socket, loaded: dict[str, Any]) -> _Stage | None:
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
    path = stage_path(request)
    # not its caller's rights, or libraries its path finds elsewhere: a fresh interpreter
    if differs := identity_differences(identity(), identity(peer)):
        _refuse(conn, fds, peer, f"its {', '.join(differs)} differ from the server's")
    if moved := elsewhere(loaded, path):
        _refuse(conn, fds, peer, f"its import path finds {', '.join(moved)} elsewhere")
    pid = os.fork()
    if pid == 0:
        conn.close()
        return _become_stage(request, fds, path)
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


def _refuse(conn: socket.socket, fds: list[int], peer: int, why: str) -> NoReturn:
    """Tell the caller to run the stage itself, and end this supervisor."""
    for fd in fds:
        os.close(fd)
    print(f"preload: refused caller {peer}: {why}", flush=True)
    # the whole request was read first and the caller closes after reading the answer: an answer
    # sent to a caller still writing, or a close with its data unread, would reach it as a broken
    # connection (no server) instead of a refusal
    with contextlib.suppress(OSError):
        conn.sendall(f"{REFUSED} {why}\n".encode())
        conn.settimeout(5.0)
        while conn.recv(64):
            pass
    os._exit(0)


def _become_stage(request: dict[str, Any], fds: list[int], path: list[str]) -> _Stage:
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
    return _Stage(list(request["argv"]), path)


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
