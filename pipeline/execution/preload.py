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

The import path (PYTHONPATH) is not part of the key: copies of a project each put their own client/ on
it, and one server serves them all. The caller sends the path a fresh interpreter would have
(`fresh_path`), the stage imports with it, and the server serves only a caller whose path finds every
library the server loaded where the server found it.

One server per user, Python and environment key, in a private folder (`socket_dir`; its log beside
the socket); it exits after `IDLE_S` without a stage. `NEEDLECUE_PRELOAD=0` turns it off (every
stage a fresh interpreter).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import signal
import site
import socket
import struct
import subprocess
import sys
import tempfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

PROTOCOL = "needlecue-preload/3"
# the server's answer to a caller with another identity, or whose import path finds its libraries elsewhere
REFUSED = "refused"
OFF = "NEEDLECUE_PRELOAD"  # "0": no server, every stage a fresh interpreter
DIR_ENV = "NEEDLECUE_PRELOAD_DIR"  # where the sockets live (default: a private folder in the temp dir)
# read by the stages when they run, never by a library as it loads: they may differ between the
# callers of one server (each stage gets the caller's whole environment)
RUNTIME_PREFIXES = ("MLFLOW_", "AWS_", "PYTEST_", "DVC_", "GIT_", "NEEDLECUE_")
RUNTIME_NAMES = frozenset({"PWD", "OLDPWD", "SHLVL", "_", "COLUMNS", "LINES"})
PATH_VAR = "PYTHONPATH"  # not keyed on (but where `fresh_path` cannot tell): the request holds the path
MAX_LOG_BYTES = 1 << 20  # a server's log (a line per stage) starts over past this
MAX_SOCKET_PATH = 100  # bytes: Linux takes 107 (macOS 103) in a Unix socket's address
CODE_FILES = ("preload.py", "preload_server.py")  # the caller's side and the server's: part of the key


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


def identity_differences(mine: Mapping[str, str], theirs: Mapping[str, str]) -> list[str]:
    """The identity fields that differ (all of them when either is unknown)."""
    if not mine or not theirs:
        return ["unknown identity"]
    return sorted(k for k in set(mine) | set(theirs) if mine.get(k) != theirs.get(k))


def key(env: Mapping[str, str]) -> str:
    """What a server must share with its callers: this Python and its installed packages, the code of
    both its sides (CODE_FILES), every environment variable a library could read as it loads (but the
    import path where the caller can send it: the server checks that one), and the caller's identity
    (a stage runs as its caller)."""
    loading = {k: v for k, v in env.items() if k not in RUNTIME_NAMES and not k.startswith(RUNTIME_PREFIXES)}
    if fresh_path(env) is not None:  # sent with the request, and checked by the server
        loading.pop(PATH_VAR, None)
    # an install or upgrade changes its site-packages folder: a new server, never a stale library
    installed = [os.stat(p).st_mtime_ns for p in site.getsitepackages() if os.path.isdir(p)]
    code = [Path(__file__).with_name(name).read_text() for name in CODE_FILES]
    doc = [PROTOCOL, sys.executable, sys.version, installed, code, sorted(loading.items()), identity()]
    return hashlib.sha256(json.dumps(doc).encode()).hexdigest()[:32]


def fresh_path(env: Mapping[str, str]) -> list[str] | None:
    """The import path (`sys.path`) of a fresh `python -m` with `env` in this folder: this process's
    own, with env's PYTHONPATH in place of ours (as Python builds it: absolute, each folder once). None
    where ours cannot be told apart from the interpreter's own folders."""
    ours = _entries(os.environ.get(PATH_VAR, ""))
    if sys.path[1 : 1 + len(ours)] != ours or any(p.startswith((sys.prefix, sys.base_prefix)) for p in ours):
        return None
    base = sys.path[1 + len(ours) :]
    return [os.getcwd(), *dict.fromkeys([*_entries(env.get(PATH_VAR, "")), *base])]


def _entries(pythonpath: str) -> list[str]:
    return list(dict.fromkeys(os.path.abspath(p) for p in pythonpath.split(os.pathsep))) if pythonpath else []


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
        path = fresh_path(env)  # None: the server's own (the key holds the PYTHONPATH)
        request = {"argv": argv, "cwd": os.getcwd(), "env": dict(env), "cpus": _cpus(), "path": path}
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
    """One line of the server's, read a byte at a time: a stage that ends at once has its status line
    right behind its pid line, and that is the next read's."""
    data = b""
    while not data.endswith(b"\n"):
        byte = conn.recv(1)
        if not byte:
            raise ConnectionError("the preload server closed the connection")
        data += byte
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
    cmd = [sys.executable, "-m", "pipeline.execution.preload_server", str(path)]
    with contextlib.suppress(OSError, subprocess.SubprocessError):
        log_path = path.with_suffix(".log")
        big = log_path.is_file() and log_path.stat().st_size > MAX_LOG_BYTES
        log = open(log_path, "wb" if big else "ab")  # noqa: SIM115 (the server keeps it)
        with log:
            subprocess.run(cmd, env=dict(env), stdin=subprocess.DEVNULL, stdout=log, stderr=log, timeout=30)
