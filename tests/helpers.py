"""Small helpers shared by several test modules."""

from __future__ import annotations

import contextlib
import hashlib
import os
import signal
import socket
import subprocess
from pathlib import Path

import psutil


def tree_hash(root: Path) -> dict[str, str]:
    """SHA-256 of every file under `root`, by relative path: equal iff the trees are byte-identical."""
    return {
        p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


def free_port() -> int:
    """A TCP port free on 127.0.0.1 now (the OS's pick), for a server a test or benchmark starts."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def stop_group(proc: subprocess.Popen, grace_s: float = 15) -> None:
    """Stop a server started in a session of its own, with every worker it forked: SIGTERM, then
    SIGKILL after `grace_s`."""
    with contextlib.suppress(ProcessLookupError):
        os.killpg(proc.pid, signal.SIGTERM)
    try:
        proc.wait(timeout=grace_s)
    except subprocess.TimeoutExpired:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(timeout=grace_s)


def descendants(pid: int) -> dict[int, str]:
    """The command line of every process under `pid` (its children, theirs, ...), by pid."""
    lines = {}
    for child in psutil.Process(pid).children(recursive=True):
        with contextlib.suppress(psutil.NoSuchProcess, psutil.AccessDenied):  # gone while listed
            lines[child.pid] = " ".join(child.cmdline())
    return lines
