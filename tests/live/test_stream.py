"""The wire format, the stream's health and the insertions found in the signal, line by line."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pipeline.live.emulate import load_trial, schedule
from pipeline.live.health import StreamHealth
from pipeline.live.insertions import InsertionDetector
from pipeline.live.recording import escape, unescape
from pipeline.live.session import StreamSettings
from pipeline.live.wire import Banner, Sample, format_banner, format_sample, parse_line
from pipeline.sim.rigs import RIGS


def test_a_line_and_the_banner_round_trip_and_garbage_says_why() -> None:
    # given: a sample and the banner as the firmware sends them
    banner = Banner("est-7", ("fsr1", "fsr2", "fsr3"), 10, 5.0, 30.0)
    # then: they parse back to the same; garbage is a reason, never an exception
    assert parse_line(format_sample(Sample(4294967295, (0, 512, 1023))).rstrip(), 3, 1023) == Sample(
        4294967295, (0, 512, 1023)
    )
    assert parse_line(format_banner(banner).rstrip(), 3, 1023) == banner
    assert parse_line(b"12,1,2", 3, 1023) == "3 fields, expected millis and 3 counts"
    assert parse_line(b"12,1,2,1024", 3, 1023) == "a count outside 0..1023: [1, 2, 1024]"
    assert parse_line(b"\xf3\x81,2", 3, 1023) == "bytes that are not ASCII"
    assert parse_line(b"12,a,2,3", 3, 1023) == "a field that is not an integer: '12,a,2,3'"
    assert parse_line(b"# a comment", 3, 1023) is None
    assert unescape(escape(b"\xf3,\\n\x00")) == b"\xf3,\\n\x00"


def test_health_names_a_gap_late_samples_garbage_a_wrong_baud_rate_and_silence() -> None:
    h = StreamHealth(rate_hz=30.0)
    h.connected(0.0, settle_s=0.0)
    # when: samples on time, then a gap of 10 frames, then one arriving 0.3 s late
    for k in range(5):
        h.sample(k / 30, k / 30, None if k == 0 else 1 / 30)
    h.sample(15 / 30, 15 / 30, 11 / 30)
    assert "10 sample(s) lost" in h.problems(0.5)["gap"]
    h.sample(16 / 30 + 0.3, 16 / 30, 1 / 30)
    assert "late" in h.problems(1.1)
    # when: nothing but garbage for a while
    for k in range(8):
        h.garbage(3.7 + k * 0.1, "bytes that are not ASCII")
    problems = h.problems(4.5)
    assert "baud rate (115200)" in problems["baud"] and "silent" in problems
    # when: the cable goes
    h.disconnected(5.0, "read failed")
    assert list(h.problems(5.1)) == ["disconnected"]
    assert h.counts["lost_samples"] == 10 and h.counts["disconnects"] == 1


def test_an_insertion_starts_and_ends_in_the_signal_and_rest_is_read_again() -> None:
    # given: 2 s at rest, 3 s of loading, 2 s back at rest, at 30 Hz
    t = np.arange(0, 7, 1 / 30)
    load = np.clip(t - 2, 0, None) * (t < 5)
    volts = 0.5 * (1 + 0.5 * load[:, None] * np.array([1.0, 0.3, -0.2]))
    det = InsertionDetector(30.0)
    # when: pushing it sample by sample
    events = [(round(ti, 2), e) for ti, v in zip(t, volts, strict=True) if (e := det.push(ti, v))]
    # then: one insertion, from shortly after the loading starts to a second after it is back at rest
    assert [e for _, e in events] == ["start", "end"]
    assert 2.0 < events[0][0] < 2.4 and 5.9 < events[1][0] < 6.1
    assert det.rest is None  # read again before the next insertion


def test_a_board_clock_that_runs_slow_is_not_taken_for_late_samples() -> None:
    # given: an Uno whose resonator runs 0.5 % slow, every sample on time for a minute
    h = StreamHealth(rate_hz=30.0)
    h.connected(0.0, settle_s=0.0)
    for k in range(1800):
        h.sample(k / 30 * 1.005, k / 30, None if k == 0 else 1 / 30)
    # then: nothing late; a 0.4 s stall afterwards still is
    assert h.counts["late_samples"] == 0
    h.sample(1800 / 30 * 1.005 + 0.4, 1800 / 30, 1 / 30)
    assert h.counts["late_samples"] == 1


def test_a_banner_that_would_break_the_conversion_is_garbage() -> None:
    # given: banners a garbled or hostile line could carry
    for bad in (b"adc_bits=0", b"adc_bits=1100", b"vref_v=nan", b"vref_v=-5", b"rate_hz=inf"):
        # then: each is a reason (counted as garbage), never a setting
        assert isinstance(parse_line(b"#needlecue-wire/1 " + bad, 3, 1023), str), bad


def test_each_simulated_insertion_is_one_insertion_start_to_end_and_no_channel_looks_stuck(
    tmp_path: Path,
) -> None:
    # given: the built-in rig simulator's trials at two angles, played back to back with rests between
    from pipeline.config import SimulateParams
    from pipeline.sim.rig import write_new_batch

    write_new_batch(SimulateParams(), tmp_path, "b", (15.0, 60.0), 2)
    trials = [load_trial(f) for f in sorted((tmp_path / "b").glob("*.fsr.csv"))]
    settings = StreamSettings(("fsr1", "fsr2", "fsr3"))
    det = InsertionDetector(30.0)
    health = StreamHealth(30.0)
    health.connected(0.0, settle_s=0.0)
    # when: the detector reads their volts, and the health their counts
    events = []
    for at, sample in schedule(trials, pause_s=3.0):
        health.channels(at, at, sample.counts, settings.adc_max, settings.channels)
        if (e := det.push(at, settings.volts(sample.counts))) is not None:
            events.append((e, at))
    # then: one start and one end per trial, the whole insertion (10 s in, then out) in between
    assert [e for e, _ in events] == ["start", "end"] * len(trials)
    lengths = [end - start for (_, start), (_, end) in zip(events[::2], events[1::2], strict=True)]
    assert all(9.0 < n < 20.0 for n in lengths), lengths
    # and every channel of a live estimator moves, if only by its noise: none is taken for stuck
    assert health.counts["stuck_channels"] == 0


def test_a_channel_at_a_rail_is_not_taken_for_stuck_but_one_still_in_mid_range_is() -> None:
    # given: 3 s in which fsr1 rises steadily, fsr2 reads 0 (an unloaded FSR over a pull-down), fsr3
    # holds 400 exactly
    health = StreamHealth(30.0)
    health.connected(0.0, settle_s=0.0)
    for k in range(90):
        at = k / 30
        health.channels(at, at, (300 + 3 * k, 0, 400), 1023, ("fsr1", "fsr2", "fsr3"))
    # then: fsr3 is named, fsr2 is not
    problem = health.problems(3.0)["stuck"]
    assert problem.startswith("fsr3 stuck at 400") and health.counts["stuck_channels"] == 1


@pytest.mark.parametrize("rig", sorted(RIGS))
def test_no_channel_of_any_rig_in_the_family_looks_stuck(rig: str, tmp_path: Path) -> None:
    # given: each estimator design of the simulator's family, at every angle, played with rests between
    from pipeline.config import SimulateParams
    from pipeline.sim.rig import write_new_batch

    write_new_batch(SimulateParams(rig=rig), tmp_path, "b", (0.0, 15.0, 30.0, 45.0, 60.0, 75.0), 1)
    trials = [load_trial(f) for f in sorted((tmp_path / "b").glob("*.fsr.csv"))]
    banner = trials[0].banner
    health = StreamHealth(30.0)
    health.connected(0.0, settle_s=0.0)
    # when: the health reads their counts at the design's own ADC resolution
    for at, sample in schedule(trials, pause_s=3.0):
        health.channels(at, at, sample.counts, 2**banner.adc_bits - 1, banner.channels or ())
    # then: no channel is taken for stuck (the stuck rule was set on none of them)
    assert health.counts["stuck_channels"] == 0
