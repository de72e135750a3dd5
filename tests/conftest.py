"""Shared fixtures: the hand-made rig-log/1 batch and a writable copy of it."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

LAB_BENCH_A = Path(__file__).parent / "fixtures" / "rig-log" / "lab-bench-a"


@pytest.fixture
def lab_bench_a() -> Path:
    """The committed fixture folder (read it, never write it)."""
    return LAB_BENCH_A


@pytest.fixture
def raw_dir(tmp_path: Path) -> Path:
    """tmp_path/raw holding a copy of lab-bench-a that a test may break."""
    raw = tmp_path / "raw"
    shutil.copytree(LAB_BENCH_A, raw / "lab-bench-a")
    return raw
