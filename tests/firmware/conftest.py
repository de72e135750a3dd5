"""The firmware built from source for the tests (the shipped settings, the millis()-polling sketch it is
compared with, and one without the settling conversion), once per run whatever the number of workers,
and tables of pin voltages for the emulated board."""

from __future__ import annotations

import subprocess
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from filelock import FileLock

from pipeline.live import board
from pipeline.live.board import FIRMWARE
from tests.live.conftest import live_model


@dataclass(frozen=True)
class Built:
    board: Path  # the simavr harness
    firmware: Path  # needlecue.elf, the shipped settings
    hex: Path
    millis_poll: Path  # the sample clock by millis() polling (docs/live.md's old example)
    no_discard: Path  # the firmware with NC_DISCARD=0


def _make(build: Path, *args: str) -> None:
    done = subprocess.run(
        ["make", "-C", str(FIRMWARE), f"BUILD={build}", *args], capture_output=True, text=True, timeout=300
    )
    assert done.returncode == 0, (
        f"make {' '.join(args)} failed (the toolchain comes from `make setup-system`):\n{done.stdout[-2000:]}"
        f"{done.stderr[-2000:]}"
    )


@pytest.fixture(scope="session")
def built(tmp_path_factory: pytest.TempPathFactory, worker_id: str) -> Built:
    base = tmp_path_factory.getbasetemp()
    shared = base if worker_id == "master" else base.parent  # xdist: the folder every worker's temp is in
    root = shared / "firmware"
    with FileLock(shared / "firmware.lock"):
        if not (shared / "firmware.done").exists():
            _make(root / "shipped", "hex", "board")
            _make(root / "shipped", "SKETCH=millis_poll", "hex")
            _make(root / "no-discard", "DISCARD=0", "hex")
            (shared / "firmware.done").touch()
    s = root / "shipped"
    return Built(
        s / "board",
        s / "needlecue.elf",
        s / "needlecue.hex",
        s / "millis_poll.elf",
        root / "no-discard" / "needlecue.elf",
    )


def write_pins(path: Path, t_s: np.ndarray, counts: np.ndarray) -> Path:
    """A harness table: from t_s[i] on, pin k holds the voltage a 10-bit ADC reads as counts[i, k]."""
    return board.write_pins(path, t_s, board.millivolts(counts))


@pytest.fixture
def ramps(tmp_path: Path) -> tuple[Path, np.ndarray, np.ndarray]:
    """Three pins far apart that change every 50 ms for 20 s (a new value never at a sample's instant
    for long): the table, its times and its counts."""
    t = np.arange(0, 20, 0.05) + 0.0137
    k = np.arange(len(t))
    counts = np.stack([100 + (k * 7) % 300, 900 - (k * 5) % 400, 500 + (k * 11) % 200], axis=1)
    return write_pins(tmp_path / "pins.csv", t, counts), t, counts


__all__ = ["live_model"]  # the live tests' registered 30° model and calibrated unit, for the board's
