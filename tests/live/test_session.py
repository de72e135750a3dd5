"""The live chain without processes: lines in, frames, a recording, and the same frames again from it."""

from __future__ import annotations

import warnings
from pathlib import Path

import pandas as pd
import pytest

from needlecue_client import ForceClient, UncalibratedUnit
from pipeline.live.app import replay_session
from pipeline.live.display import terminal_line
from pipeline.live.emulate import load_trial, schedule
from pipeline.live.recording import SessionRecorder, read_trials
from pipeline.live.session import LiveSession, StreamSettings
from pipeline.live.wire import Sample, format_banner, format_sample
from tests.live.conftest import LiveModel, write_trials


def _feed(session: LiveSession, files: list[Path]) -> None:
    """The emulated rig's lines, stamped on time, straight into the session."""
    trials = [load_trial(f) for f in files]
    session.connected(0.0, "test", 0.0)
    session.line(0.0, format_banner(trials[0].banner).rstrip())
    for at, sample in schedule(trials, pause_s=2.5):
        session.line(at + 0.001, format_sample(sample).rstrip())


def test_an_uncalibrated_unit_gets_force_without_cues_and_the_recording_replays_the_same(
    live_model: LiveModel, tmp_path: Path
) -> None:
    # given: the champion for a unit that was never calibrated
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        client = ForceClient.from_dir(live_model.model_dir, unit_id="est-never")
    assert any(issubclass(w.category, UncalibratedUnit) for w in caught)
    states: list[dict] = []
    recorder = SessionRecorder(
        tmp_path / "s", {"sensor": {"unit_id": "est-never"}}, client.channels, targets=client.targets
    )
    session = LiveSession(
        client, StreamSettings(tuple(client.channels)), recorder=recorder, publish=states.append
    )
    # when: two insertions arrive
    _feed(session, write_trials(tmp_path / "held", [30, 45]))
    summary = session.close(100.0)
    # then: force in every insertion frame, never a cue, and the page is told why
    inside = [s for s in states if s["insertion"] is not None]
    assert inside and all(s["cue"] == "none" and s["force_n"] is not None for s in inside)
    assert not inside[-1]["calibrated"] and "calibration" in inside[-1]["uncalibrated_reason"]
    assert [i["cues"] for i in summary["insertions"]] == [["none"], ["none"]]
    # and: the banner's 12-bit ADC was taken, and the recording replays to the same insertions
    assert session.settings.adc_bits == 12
    assert [t["cues"] for t in read_trials(tmp_path / "s")] == ["none", "none"]
    assert replay_session(tmp_path / "s", client)["insertions"] == summary["insertions"]
    fsr = pd.read_csv(tmp_path / "s" / "i001.fsr.csv")
    assert list(fsr.columns) == ["t_ms", *client.channels, "board_ms"] and fsr["t_ms"].is_monotonic_increasing
    cues = pd.read_csv(tmp_path / "s" / "i001.cues.csv")
    assert list(cues.columns) == ["t_s", "cue", "angle_est_deg", "fx", "fy", "fz", "reason"]
    assert inside[-1]["targets"] == ["fx", "fy", "fz"] and len(inside[-1]["force_n"]) == 3
    assert " F=(" in terminal_line(inside[-1])


def test_a_model_of_fz_shows_and_records_fz_alone(fz_live_model: LiveModel, tmp_path: Path) -> None:
    # given: the champion of a lab whose reference recorded fz alone, and a recorded session
    with pytest.warns(UncalibratedUnit):
        client = ForceClient.from_dir(fz_live_model.model_dir, unit_id="est-never")
    states: list[dict] = []
    recorder = SessionRecorder(tmp_path / "s", {}, client.channels, targets=client.targets)
    session = LiveSession(
        client, StreamSettings(tuple(client.channels)), recorder=recorder, publish=states.append
    )
    # when: an insertion arrives
    _feed(session, write_trials(tmp_path / "held", [30]))
    session.close(100.0)
    # then: each frame's force is fz alone, named so for the page and the terminal; the recording's
    # cues.csv has an fz column and none for fx or fy
    inside = [s for s in states if s["insertion"] is not None]
    assert inside and all(s["targets"] == ["fz"] and len(s["force_n"]) == 1 for s in inside)
    line = terminal_line(inside[-1])
    assert f" fz={inside[-1]['force_n'][0]:+.2f} N" in line and "F=(" not in line
    cues = pd.read_csv(tmp_path / "s" / "i001.cues.csv")
    assert list(cues.columns) == ["t_s", "cue", "angle_est_deg", "fz", "reason"] and cues["fz"].notna().all()


def test_one_garbled_board_time_is_garbage_but_a_restarted_board_is_a_restart(
    live_model: LiveModel, tmp_path: Path
) -> None:
    # given: a session at rest, 2 s of samples from a board that has run for a while
    with pytest.warns(UncalibratedUnit):
        client = ForceClient.from_dir(live_model.model_dir, unit_id="est-live")
    session = LiveSession(client, StreamSettings(tuple(client.channels)))
    session.connected(0.0, "test", 0.0)
    for k in range(60):
        session.line(k / 30, format_sample(Sample(900_000 + k * 33, (400, 300, 350))).rstrip())
    # when: one line's millis lost a digit, then the board goes on
    session.line(2.0, b"90198,400,300,350")
    session.line(2.03, format_sample(Sample(900_000 + 61 * 33, (400, 300, 350))).rstrip())
    # then: garbage, not a restart; the clock went on
    assert session.health.counts["garbage_lines"] == 1 and "restart" not in session.notes
    # when: the board really restarts (its millis start again near zero)
    session.line(2.06, format_sample(Sample(1500, (400, 300, 350))).rstrip())
    assert "restart" in session.notes and session.health.counts["samples"] == 62
