"""The done-when of issue 15: `needlecue emulate-rig` on one end of a pseudo-terminal, `needlecue live`
on the other, a real headless Chromium on the trainee's page. Real processes, real rate (about 20 s)."""

from __future__ import annotations

import csv
import shutil
import time
from pathlib import Path

import pytest

from tests.live.conftest import UNIT, LiveModel
from tests.live.processes import rig_and_live

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
pytestmark = pytest.mark.xdist_group("live")  # one real-time session at a time


def _all_ended(page: object, n: int) -> bool:
    items = page.locator("#history li").all_text_contents()  # type: ignore[attr-defined]
    return len(items) >= n and all(item.endswith(")") for item in items)


def test_emulated_rig_to_the_trainee_page_and_the_recording(live_model: LiveModel, tmp_path: Path) -> None:
    from playwright.sync_api import sync_playwright

    # given: an on-angle, a 15°-off and a 30°-off insertion for the 30° champion, played by the emulated rig
    # when: needlecue live reads it with the unit's calibration, and a browser shows its page
    live_args = ["--angle", "30", "--insertions", "3", "--give-up", "10"]
    with rig_and_live(live_model, tmp_path, [30, 45, 60], [], live_args) as run:
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=["--disable-gpu"], timeout=30_000)
            page = browser.new_page(viewport={"width": 1200, "height": 700})
            page.goto(run.url)
            end = time.monotonic() + 90
            while time.monotonic() < end and not _all_ended(page, 3):
                time.sleep(0.1)
            history = page.locator("#history li").all_text_contents()
            # what the page records: each insertion's cues in the history, each in its cue's colour
            # (not a sample of the big cue taken at the right moment: a busy machine may start the
            # browser after the first insertion has ended)
            chips = page.locator("#history span[data-cue]")
            seen = dict(
                zip(
                    chips.evaluate_all("es => es.map(e => e.dataset.cue)"),
                    chips.evaluate_all("es => es.map(e => getComputedStyle(e).backgroundColor)"),
                    strict=True,
                )
            )
            unit_text = page.locator("#unit").text_content()
            page.screenshot(path=str(tmp_path / "page.png"))
            browser.close()
        out, _ = run.live.communicate(timeout=60)

    # then: the page listed each insertion's cue sequence, ending on the right cue, in the cue's colour
    assert history == [
        "#1 wait → continue (end)",
        "#2 wait → correct (end)",
        "#3 wait → none → stop (end)",  # a moment of "no angle cue" before the evidence decides
    ], out
    assert {"continue", "correct", "stop"} <= set(seen), seen
    assert len({seen["continue"], seen["correct"], seen["stop"], seen["none"]}) == 4  # four colours
    assert unit_text == f"unit {UNIT} (calibrated)"
    # and the recording holds the same insertions, which needlecue replay plays back the same
    session = run.session
    with (session / "trials.csv").open() as f:
        recorded = [(r["trial_id"], r["cues"], r["ended"]) for r in csv.DictReader(f)]
    assert recorded == [
        ("i001", "wait continue", "end"),
        ("i002", "wait correct", "end"),
        ("i003", "wait none stop", "end"),
    ]
    assert (session / "i001.fsr.csv").read_text().startswith("t_ms,fsr1,fsr2,fsr3,board_ms\n")
    replayed = run.replay(str(session), "--model-dir", str(live_model.model_dir), "--unit-id", UNIT)
    assert "insertion 3 (i003): wait -> none -> stop (as live)" in replayed.stdout
