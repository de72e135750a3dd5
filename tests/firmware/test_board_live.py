"""The done-when of issue 29: the shipped firmware on an emulated board (simavr), its serial port a
pseudo-terminal that `needlecue live` reads as it would a real Uno's. Real processes at the real rate,
each run bounded (about 20 s)."""

from __future__ import annotations

import csv
import itertools
import json
import os
import re
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from pipeline.live import board as bd
from pipeline.live.recording import unescape
from pipeline.live.wire import Sample, parse_banner, parse_line
from tests.firmware.conftest import Built, write_pins
from tests.live.conftest import UNIT, LiveModel
from tests.live.processes import NEEDLECUE, Running, rig_and_live, watch_problems

pytestmark = pytest.mark.xdist_group("live")  # one real-time session at a time
CUE_LINE = re.compile(r"^\s*-?\d+\.\d+ s  (\w+)")


def board_args(built: Built, *more: str) -> list[str]:
    return ["--elf", str(built.firmware), "--board", str(built.board), *more]


def recorded_lines(session: Path) -> list[tuple[float, bytes]]:
    with (session / "lines.csv").open() as f:
        return [(float(r["host_s"]), unescape(r["text"])) for r in csv.DictReader(f) if r["kind"] == "line"]


def replayed_cues(run: Running, trial: Path, model: LiveModel, tmp_path: Path) -> list[str]:
    """The cue sequence `needlecue replay` gives the trial's file."""
    out = tmp_path / f"{trial.stem}.png"
    done = run.replay(str(trial), "--model-dir", str(model.model_dir), "--unit-id", UNIT, "--out", str(out))
    return [m.group(1) for line in done.stdout.splitlines() if (m := CUE_LINE.match(line))]


def test_live_on_the_emulated_board_gives_the_cues_replay_gives_at_the_declared_rate(
    built: Built, live_model: LiveModel, tmp_path: Path
) -> None:
    # given: an on-angle, a 15°-off and a 30°-off insertion for the 30° champion, each ending with the
    # needle withdrawn (so that live's insertion is the trial's, not the rest after it), in 10-bit
    # counts, on the pins of the emulated board running the shipped firmware
    live_args = ["--angle", "30", "--insertions", "3", "--give-up", "10"]
    with rig_and_live(
        live_model,
        tmp_path,
        [30, 15, 0],
        board_args(built),
        live_args,
        rig="emulate-board",
        adc_bits=10,
        withdraw=True,
    ) as run:
        # when: needlecue live reads its pseudo-terminal
        out, _ = run.live.communicate(timeout=90)
        board_out, _ = run.rig.communicate(timeout=30)  # the board stops 1 s after the last rest
    assert run.live.returncode == 0, out
    assert run.rig.returncode == 0, board_out
    # then: each insertion showed the cues `needlecue replay` gives its trial's file
    with (run.session / "trials.csv").open() as f:
        recorded = list(csv.DictReader(f))
    assert [r["ended"] for r in recorded] == ["end"] * 3, out
    live_cues = [r["cues"].split() for r in recorded]
    replay_cues = [replayed_cues(run, trial, live_model, tmp_path) for trial in run.files]
    print("live", live_cues, "replay", replay_cues)
    assert live_cues == replay_cues
    assert [cues[-1] for cues in live_cues] == ["continue", "correct", "stop"]
    # and the stream is the firmware's: its banner, then samples at the declared rate within 0.1 %
    lines = recorded_lines(run.session)
    banner = parse_banner(lines[0][1].decode())
    assert banner.channels == ("fsr1", "fsr2", "fsr3") and banner.adc_bits == 10
    assert b"fw=needlecue-fw/1" in lines[0][1]
    millis = [s.millis for _, raw in lines if isinstance(s := parse_line(raw, 3, 1023), Sample)]
    rate = (len(millis) - 1) * 1000 / (millis[-1] - millis[0])
    assert abs(rate / banner.rate_hz - 1) <= 1e-3, rate
    assert all(0 < b - a < 40 for a, b in itertools.pairwise(millis))  # no gap, nothing lost
    summary = bd.summary(board_out)
    print(f"board: {summary}; stream rate {rate:.4f} Hz over {len(millis)} samples")
    assert summary["lost_bytes"] == 0 and summary["resets"] == 0


def test_an_overrun_a_reset_and_a_stuck_channel_on_the_board_are_shown_and_recorded(
    built: Built, live_model: LiveModel, tmp_path: Path
) -> None:
    # given: three on-angle insertions (board time: loading from about 3.7, 9.2 and 14.7 s); the board
    # resets at 9.7 s, mid-insertion; fsr2's pin sticks at 1 V from 13 s on; its USB link holds 1 KiB
    stuck = bd.Stuck(1, 13.0, 60.0, 1000).arg()
    rig_args = board_args(
        built, "--reset-at", "9.7", "--stuck", stuck, "--dev-buf", "1024", "--seconds", "26"
    )
    live_args = ["--angle", "30", "--duration", "21", "--give-up", "5"]
    with rig_and_live(
        live_model, tmp_path, [30, 30, 30], rig_args, live_args, rig="emulate-board", adc_bits=10
    ) as run:
        started = time.monotonic()
        # when: the host stops reading for 3.5 s during the first insertion (live suspended)
        time.sleep(3.0)
        os.kill(run.live.pid, signal.SIGSTOP)
        time.sleep(3.5)
        os.kill(run.live.pid, signal.SIGCONT)
        seen = watch_problems(run, started + 40 - time.monotonic())
        out, _ = run.live.communicate(timeout=30)
        board_out, _ = run.rig.communicate(timeout=30)
    assert run.live.returncode == 0, out
    summary = bd.summary(board_out)
    # then: the link lost what the host did not take, and the board went on regardless
    assert summary["lost_bytes"] > 0 and summary["resets"] == 1, summary
    # and live showed and counted the gap, the late burst, the restart and the stuck channel
    session = json.loads((run.session / "session.json").read_text())
    counts, insertions = session["counts"], session["insertions"]
    print(counts, [(i["trial_id"], i["ended"], i["cues"]) for i in insertions], sorted(seen))
    assert counts["gaps"] >= 1 and counts["lost_samples"] >= 10 and counts["late_samples"] >= 1
    assert counts["stuck_channels"] == 1
    assert {"gap", "late", "stuck"} <= seen
    assert [i["ended"] for i in insertions].count("restart") == 1
    banners = [raw for _, raw in recorded_lines(run.session) if raw.startswith(b"#needlecue-wire/1")]
    assert len(banners) == 2  # after power-on and after the reset


def test_unit_id_sets_the_id_the_board_keeps_in_its_eeprom(built: Built, tmp_path: Path) -> None:
    table = write_pins(tmp_path / "pins.csv", np.array([0.0]), np.array([[100, 200, 300]]))
    eeprom, link = tmp_path / "eeprom.bin", tmp_path / "board"
    args = bd.command(built.firmware, table, board=built.board, link=link, eeprom=eeprom, seconds=60.0)

    def unit_id(*more: str) -> subprocess.CompletedProcess[str]:
        cmd = [*NEEDLECUE, "unit-id", "--port", str(link), "--reset-wait", "0.3", *more]
        return subprocess.run(cmd, capture_output=True, text=True, timeout=60)

    def power_on() -> subprocess.Popen[str]:
        proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        end = time.monotonic() + 10
        while not link.exists() and time.monotonic() < end:
            time.sleep(0.02)
        return proc

    # given: a new board (blank EEPROM)
    board = power_on()
    try:
        # when: a lab gives it an id over serial
        set_it = unit_id("est-777")
        refused = unit_id("bad id!")
    finally:
        board.terminate()  # the harness keeps the EEPROM in its file on the way out
        board.communicate(timeout=10)
    assert set_it.returncode == 0, set_it.stdout + set_it.stderr
    assert "unit est-777; channels fsr1,fsr2,fsr3; 30 Hz" in set_it.stdout
    assert refused.returncode == 1 and "1 to 23 of A-Z a-z 0-9 . _ -" in refused.stderr
    # then: powered again, the board still has it, and --clear takes it away
    board = power_on()
    try:
        shown, cleared = unit_id(), unit_id("--clear")
    finally:
        board.terminate()
        board.communicate(timeout=10)
    assert shown.returncode == 0 and "unit est-777;" in shown.stdout, shown.stdout + shown.stderr
    assert cleared.returncode == 0 and "unit (none);" in cleared.stdout, cleared.stdout + cleared.stderr
