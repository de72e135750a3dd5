"""DVC in this process, its log records shown on the caller's log: `dvc status` (`dvc_changed`) and
`dvc repro` (`dvc_repro`), for `needlecue retrain`."""

from __future__ import annotations

import logging
import os
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from pipeline.logs import Log

logger = logging.getLogger(__name__)


class Busy(RuntimeError):
    """Another process holds the project: another retrain (its lock), or a DVC command (DVC's)."""


class _ToLog(logging.Handler):
    """DVC's progress messages ("Running stage 'x':", the command) to the retrain's log."""

    def __init__(self, log: Log) -> None:
        super().__init__(logging.INFO)
        self.log = log

    def emit(self, record: logging.LogRecord) -> None:
        message = record.getMessage()
        if message.strip():
            self.log(f"dvc: {message}")


@contextmanager
def dvc_repo(root: Path, log: Log) -> Iterator[Any]:
    """The project's DVC repo, its log records shown on `log` while it is open.

    DVC runs in this process, not as a `dvc` child: DVC's stage locks name the process holding them,
    and a killed `dvc` child whose parent died too stays a zombie where nothing reaps orphans (a
    container without an init), which DVC takes for a live holder and waits for. This process's
    own parent (cron, systemd, a shell) reaps it."""
    from dvc.lock import LockError
    from dvc.repo import Repo

    handler, dvc_log = _ToLog(log), logging.getLogger("dvc")
    level = dvc_log.level
    dvc_log.addHandler(handler)
    dvc_log.setLevel(logging.INFO)
    try:
        with Repo(str(root)) as repo:
            yield repo
    except LockError as e:
        raise Busy(
            f"another DVC command is running in {root}: nothing done ({str(e).splitlines()[0]})"
        ) from e
    finally:
        dvc_log.removeHandler(handler)
        dvc_log.setLevel(level)


def dvc_changed(root: Path, log: Log = logger.info) -> list[str]:
    """Stages DVC reports as out of date (`dvc status`)."""
    with dvc_repo(root, log) as repo:
        return sorted(repo.status())


def _stage_states(root: Path) -> dict[str, Any]:
    """dvc.lock's record of every stage (what each last ran on and wrote)."""
    import yaml

    lock = root / "dvc.lock"
    return (yaml.safe_load(lock.read_text()) or {}).get("stages", {}) if lock.is_file() else {}


def dvc_repro(root: Path, log: Log) -> tuple[int, list[str], list[str]]:
    """`dvc repro` (its progress and the stages' output on this process's): (exit code, stages run,
    the error's lines). After a failure, the stages run are those whose dvc.lock record changed:
    the ones that completed before it."""
    from dvc.exceptions import DvcException

    before = _stage_states(root)
    python = {"PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}"}
    try:
        with dvc_repo(root, log) as repo:
            ran = repo.reproduce(run_env=python)  # stages call `python`: this interpreter's
        return 0, [stage.addressing for stage in ran], []
    except DvcException as e:
        after = _stage_states(root)
        done = [name for name, state in after.items() if before.get(name) != state]
        lines = [str(e)] + ([f"caused by: {e.__cause__}"] if e.__cause__ else [])
        log(f"dvc repro failed: {' '.join(lines)}")
        return 1, done, lines
