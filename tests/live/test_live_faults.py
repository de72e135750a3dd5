"""Faults on the wire, with the real processes: the display says what is wrong, nothing crashes, and
the recording keeps what arrived. Each run is bounded (--duration, --give-up) to under 30 s."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest

from tests.live.conftest import LiveModel
from tests.live.processes import rig_and_live, watch_problems

pytestmark = pytest.mark.xdist_group("live")


def _run(
    model: LiveModel, tmp_path: Path, rig_args: list[str], live_args: list[str]
) -> tuple[set[str], str, Path]:
    """emulate-rig with `rig_args` against live with `live_args`: the problem keys the page's state
    showed, live's output and the session folder."""
    with rig_and_live(model, tmp_path, [30, 45], rig_args, live_args) as run:
        seen = watch_problems(run, 60)
        out, _ = run.live.communicate(timeout=30)
        assert run.live.returncode == 0, out
    return seen, out, run.session


def test_garbage_a_stall_and_a_pulled_cable_are_shown_and_recorded(
    live_model: LiveModel, tmp_path: Path
) -> None:
    # given: garbage at 1 s, a 0.6 s USB stall at 2 s, the cable pulled at 4.8 s (mid-insertion: the
    # first one loads from 3.5 s) and plugged in 1 s later
    rig_args = [
        "--garbage-at",
        "1",
        "--stall-at",
        "2",
        "--stall",
        "0.6",
        "--pull-at",
        "4.8",
        "--replug-after",
        "1",
    ]
    # when: live runs through it
    seen, out, session = _run(live_model, tmp_path, rig_args, ["--duration", "14", "--give-up", "5"])
    # then: the page said each fault, live went on after the replug, and the recording has it all
    assert {"garbage", "late", "disconnected"} <= seen, (seen, out)
    with (session / "lines.csv").open() as f:
        kinds = [row["kind"] for row in csv.DictReader(f)]
    assert kinds.count("connect") == 2 and kinds.count("disconnect") >= 1  # the pull (and the end)
    summary = json.loads((session / "session.json").read_text())
    assert summary["counts"]["garbage_lines"] >= 1 and summary["counts"]["late_samples"] >= 1
    assert summary["counts"]["samples"] > 300  # samples kept coming after the replug
    assert summary["insertions"][0]["ended"] == "disconnected"  # the pull cut the first insertion short


def test_a_wrong_baud_rate_is_named_on_the_page(live_model: LiveModel, tmp_path: Path) -> None:
    # given: firmware at 9600 baud, the port opened at 115200
    seen, out, session = _run(live_model, tmp_path, ["--baud", "9600"], ["--duration", "5"])
    # then: the page said the baud rate looks wrong; no sample was taken from garbage
    assert "baud" in seen, (seen, out)
    summary = json.loads((session / "session.json").read_text())
    assert summary["counts"].get("samples", 0) == 0 and summary["counts"]["garbage_lines"] > 0
