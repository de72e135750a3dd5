"""Small helpers shared by several test modules."""

from __future__ import annotations

import contextlib
import hashlib
import os
import signal
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


def descendants(pid: int) -> list[str]:
    """The command line of every process under `pid` (its children, theirs, ...)."""
    lines = []
    for child in psutil.Process(pid).children(recursive=True):
        with contextlib.suppress(psutil.NoSuchProcess, psutil.AccessDenied):  # gone while listed
            lines.append(" ".join(child.cmdline()))
    return lines
