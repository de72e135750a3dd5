"""The done-when of issue 15: `needlecue emulate-rig` on one end of a pseudo-terminal, `needlecue live`
on the other, a real headless Chromium on the trainee's page. Real processes, real rate (about 20 s)."""

from __future__ import annotations

import csv
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.live.conftest import UNIT, LiveModel, write_trials

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
NEEDLECUE = [sys.executable, "-m", "pipeline.cli"]
pytestmark = pytest.mark.xdist_group("live")  # one real-time session at a time


def _env(model: LiveModel, tmp_path: Path) -> dict[str, str]:
    env = dict(os.environ)
    env.update(MLFLOW_TRACKING_URI=model.uri, MLFLOW_REGISTRY_URI=model.uri)
    env["NEEDLECUE_MODEL_CACHE"] = str(tmp_path / "cache")
    return env


def _display_url(proc: subprocess.Popen[str], limit_s: float = 60) -> str:
    end = time.monotonic() + limit_s
    assert proc.stdout is not None
    said = []
    while time.monotonic() < end:
        line = proc.stdout.readline()
        said.append(line)
        if line.startswith("display: "):
            return line.split()[1]
        if not line and proc.poll() is not None:
            break
    raise AssertionError(f"needlecue live printed no display URL (exit {proc.poll()}): {''.join(said)}")


def _all_ended(page: object, n: int) -> bool:
    items = page.locator("#history li").all_text_contents()  # type: ignore[attr-defined]
    return len(items) >= n and all(item.endswith(")") for item in items)


def test_emulated_rig_to_the_trainee_page_and_the_recording(live_model: LiveModel, tmp_path: Path) -> None:
    from playwright.sync_api import sync_playwright

    # given: an on-angle, a 15°-off and a 30°-off insertion for the 30° champion, played by the emulated rig
    files = write_trials(tmp_path / "held", [30, 45, 60])
    link, session = tmp_path / "rig", tmp_path / "session"
    env = _env(live_model, tmp_path)
    rig = subprocess.Popen(
        [*NEEDLECUE, "emulate-rig", *map(str, files), "--link", str(link), "--pause", "2.5"],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    live = None
    try:
        deadline = time.monotonic() + 30
        while not link.exists() and time.monotonic() < deadline:
            time.sleep(0.05)
        # when: needlecue live reads it with the unit's calibration, and a browser shows its page
        live = subprocess.Popen(
            [
                *NEEDLECUE,
                "live",
                "--port",
                str(link),
                "--model-dir",
                str(live_model.model_dir),
                "--angle",
                "30",
                "--unit",
                UNIT,
                "--record",
                str(session),
                "--http-port",
                "0",
                "--insertions",
                "3",
                "--reset-wait",
                "0.5",
                "--give-up",
                "10",
            ],
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        url = _display_url(live)
        seen: dict[str, str] = {}  # cue shown -> its background colour
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=["--disable-gpu"], timeout=30_000)
            page = browser.new_page(viewport={"width": 1200, "height": 700})
            page.goto(url)
            end = time.monotonic() + 90
            while time.monotonic() < end and not _all_ended(page, 3):
                cue = page.locator("#cue")
                seen[cue.get_attribute("data-cue") or ""] = cue.evaluate(
                    "e => getComputedStyle(e).backgroundColor"
                )
                time.sleep(0.05)
            history = page.locator("#history li").all_text_contents()
            unit_text = page.locator("#unit").text_content()
            page.screenshot(path=str(tmp_path / "page.png"))
            browser.close()
        out, _ = live.communicate(timeout=60)
    finally:
        for proc in (live, rig):
            if proc is not None and proc.poll() is None:
                proc.kill()
                proc.wait(timeout=10)

    # then: the page listed each insertion's cue sequence, ending on the right cue, in the cue's colour
    assert history == [
        "#1 wait → continue (end)",
        "#2 wait → correct (end)",
        "#3 wait → stop (end)",
    ], out
    assert {"continue", "correct", "stop"} <= set(seen), seen
    assert len({seen["continue"], seen["correct"], seen["stop"]}) == 3  # three colours
    assert unit_text == f"unit {UNIT} (calibrated)"
    # and the recording holds the same insertions, which needlecue replay plays back the same
    with (session / "trials.csv").open() as f:
        recorded = [(r["trial_id"], r["cues"], r["ended"]) for r in csv.DictReader(f)]
    assert recorded == [
        ("i001", "wait continue", "end"),
        ("i002", "wait correct", "end"),
        ("i003", "wait stop", "end"),
    ]
    assert (session / "i001.fsr.csv").read_text().startswith("t_ms,fsr1,fsr2,fsr3,board_ms\n")
    replayed = subprocess.run(
        [*NEEDLECUE, "replay", str(session), "--model-dir", str(live_model.model_dir), "--unit-id", UNIT],
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert replayed.returncode == 0, replayed.stdout + replayed.stderr
    assert "insertion 3 (i003): wait -> stop (as live)" in replayed.stdout
