"""The shipped firmware, built from source, on simavr's ATmega328P as fast as the host runs it: what it
sends, how well its sample clock keeps time, and the faults a board can cause. Board time is counted
in the emulator's cycles, so these figures do not depend on the load of the machine."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pipeline.live import board as bd
from pipeline.live.health import StreamHealth
from pipeline.live.wire import Banner, Sample, parse_banner, parse_line
from tests.firmware.conftest import Built

NAMES = ("fsr1", "fsr2", "fsr3")


def run(built: Built, table: Path, tmp: Path, seconds: float, elf: Path | None = None, **kw: object):
    """Run the board; (summary, the lines it sent, the instants of the samples it sent in board
    seconds). The run may stop between a sample and its line: that last instant is left out."""
    tx, events = tmp / "tx.bin", tmp / "events.txt"
    args = bd.command(
        elf or built.firmware, table, board=built.board, tx=tx, events=events, seconds=seconds, **kw
    )
    summary = bd.run(args, timeout_s=120)
    lines = tx.read_bytes().split(b"\n")[:-1]
    instants = bd.sample_instants(events)
    sent = len(samples(lines))
    assert sent <= len(instants) <= sent + 1 + summary["resets"]  # a reset loses the sample under way
    return summary, lines, instants if summary["resets"] else instants[:sent]


def samples(lines: list[bytes]) -> list[Sample]:
    return [s for raw in lines if isinstance(s := parse_line(raw, 3, 1023), Sample)]


def rows_at(t: np.ndarray, table_t: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """The table's counts in force at times t."""
    return counts[np.clip(np.searchsorted(table_t, t, side="right") - 1, 0, None)]


def test_the_hex_is_intel_hex_that_fits_an_uno_beside_its_bootloader(built: Built) -> None:
    data = 0
    lines = built.hex.read_text().split()
    for line in lines:
        record = bytes.fromhex(line[1:])
        assert line[0] == ":" and sum(record) % 256 == 0, line  # every record's checksum
        data += record[0] if record[3] == 0 else 0
    assert lines[-1] == ":00000001FF"
    assert 1000 < data <= 32 * 1024 - 512  # optiboot keeps the last 512 bytes of the 32 KiB


def test_the_banner_says_what_it_is_and_every_count_is_the_pins_voltage(
    built: Built, ramps: tuple[Path, np.ndarray, np.ndarray], tmp_path: Path
) -> None:
    # given: pins that change every 50 ms, and a sample-and-hold that keeps 20 % of the previous pin
    table, t, counts = ramps
    # when: the firmware runs 10 s
    _summary, lines, instants = run(built, table, tmp_path, 10.0)
    # then: a banner first, saying the channels, the converter, the rate and the oversampling
    assert lines[0].startswith(b"#needlecue-wire/1 ")
    assert parse_banner(lines[0].decode()) == Banner(None, NAMES, 10, 5.0, 30.0)
    assert b" oversample=4 fw=needlecue-fw/1" in lines[0]
    # and one line per sample instant, each count the voltage on its pin then, exactly: the discarded
    # conversion after each switch of the multiplexer absorbs what the previous pin left
    got = samples(lines)
    assert len(got) == len(instants) == pytest.approx((10 - bd.BOOT_MS / 1000) * 30, abs=1)
    sent = np.array([s.counts for s in got])
    now, soon = rows_at(instants, t, counts), rows_at(instants + 0.002, t, counts)
    assert np.all((sent == now) | (sent == soon))
    assert not [raw for raw in lines if raw.startswith(b"#missed")]


def test_without_the_settling_conversion_the_previous_pin_leaks_in(
    built: Built, ramps: tuple[Path, np.ndarray, np.ndarray], tmp_path: Path
) -> None:
    # given: the firmware built with NC_DISCARD=0
    table, t, counts = ramps
    _, lines, instants = run(built, table, tmp_path, 10.0, elf=built.no_discard)
    sent = np.array([s.counts for s in samples(lines)])
    error = np.abs(sent - rows_at(instants, t, counts))
    # then: nearly every count is off, by a share of the difference from the pin read before it
    assert (error > 1).mean() > 0.8 and error.mean() > 5


def test_the_sample_clock_keeps_the_declared_rate_and_millis_polling_does_not(
    built: Built, ramps: tuple[Path, np.ndarray, np.ndarray], tmp_path: Path
) -> None:
    table = ramps[0]
    figures = {}
    for name, elf in (("timer1", built.firmware), ("millis_poll", built.millis_poll)):
        (tmp_path / name).mkdir()
        _, lines, instants = run(built, table, tmp_path / name, 30.0, elf=elf)
        declared = parse_banner(lines[0].decode()).rate_hz
        assert declared == 30.0
        figures[name] = bd.clock_figures(instants[1:], declared)  # the first follows the boot
        got = samples(lines)
        figures[name + "_millis"] = (len(got) - 2) * 1000 / (got[-1].millis - got[1].millis)
    print(figures)
    timer, poll = figures["timer1"], figures["millis_poll"]
    # then: the firmware's rate within 0.1 % of its banner's, in board time and in its own millis,
    # and no period more than 1 % off the mean (the ADC interrupt chain only ever waits for another ISR)
    assert abs(timer.rate_error) <= 1e-3 and abs(figures["timer1_millis"] / 30 - 1) <= 1e-3
    assert timer.jitter <= 0.01 and timer.samples >= 890
    # while millis() polling misses both: its period is whole milliseconds plus the prints' time
    assert abs(poll.rate_error) > 1e-3 and poll.jitter > 0.01


def test_a_slow_crystal_slows_the_clock_but_the_host_takes_it_for_drift_not_lateness(
    built: Built, ramps: tuple[Path, np.ndarray, np.ndarray], tmp_path: Path
) -> None:
    # given: a crystal 0.5 % slow (the firmware still counts on 16 MHz)
    faults = bd.BoardFaults(freq_hz=15_920_000)
    _, lines, instants = run(built, ramps[0], tmp_path, 20.0, faults=faults)
    clock = bd.clock_figures(instants[1:], 30.0)
    assert clock.rate_error == pytest.approx(-0.005, abs=2e-4) and clock.jitter <= 0.01
    # when: the host reads each line 2 ms after it was sampled
    got = samples(lines)
    health = StreamHealth(rate_hz=30.0)
    health.connected(0.0, settle_s=0.0)
    for k, (at, s) in enumerate(zip(instants, got, strict=True)):
        gap = None if k == 0 else (s.millis - got[k - 1].millis) / 1000
        health.sample(at + 0.002, s.millis / 1000, gap)
    # then: the board's millis run 0.5 % slow against true time, and nothing is late, lost or off-rate
    assert (got[-1].millis - got[1].millis) / 1000 / (instants[-1] - instants[1]) == pytest.approx(
        0.995, abs=1e-3
    )
    assert health.counts["late_samples"] == 0 and health.counts["gaps"] == 0
    assert "rate" not in health.problems(instants[-1])


def test_a_reset_mid_session_sends_the_banner_again_and_millis_start_over(
    built: Built, ramps: tuple[Path, np.ndarray, np.ndarray], tmp_path: Path
) -> None:
    # given: a reset at 4 s
    summary, lines, _instants = run(built, ramps[0], tmp_path, 8.0, faults=bd.BoardFaults(reset_at_s=(4.0,)))
    banners = [k for k, raw in enumerate(lines) if raw.startswith(b"#needlecue-wire/1")]
    # then: the banner after power-on and after the reset, and millis from zero after each
    assert summary["resets"] == 1 and len(banners) == 2
    after = samples(lines[banners[1] :])
    before = samples(lines[: banners[1]])
    assert after[0].millis < 40 and before[-1].millis > 3700
    assert np.all(np.diff([s.millis for s in after]) > 0)
    # and sampling went on: 4 s before, the boot wait, 4 s after, less the boot after the reset
    assert len(before) + len(after) == pytest.approx((8.0 - 2 * bd.BOOT_MS / 1000) * 30, abs=2)


def test_the_unit_id_is_set_over_serial_and_kept_in_eeprom(
    built: Built, ramps: tuple[Path, np.ndarray, np.ndarray], tmp_path: Path
) -> None:
    eeprom = tmp_path / "eeprom.bin"
    # given: a new board (blank EEPROM): no unit in its banner
    # when: the host sends an id, a bad one, and asks for the banner
    commands = [(1.0, "ID est-042\n"), (1.5, "ID bad id!\n"), (2.0, "?\n"), (2.2, "RESET\n")]
    (tmp_path / "a").mkdir()
    _, lines, _ = run(built, ramps[0], tmp_path / "a", 3.0, eeprom=eeprom, rx_at=commands)
    comments = [raw.decode() for raw in lines if raw.startswith(b"#")]
    assert parse_banner(comments[0]).unit_id is None
    assert comments[1:] == [
        "#id unit=est-042 saved",
        "#error id: 0 to 23 of A-Z a-z 0-9 . _ -",
        comments[0].replace("#needlecue-wire/1 ", "#needlecue-wire/1 unit=est-042 "),
        "#error unknown command (ID <unit>, ID, ?)",
    ]
    assert len(samples(lines)) == pytest.approx((3.0 - bd.BOOT_MS / 1000) * 30, abs=1)  # no sample lost
    # when: the board is powered again with the same EEPROM, then the id is cleared
    (tmp_path / "b").mkdir()
    _, lines, _ = run(
        built, ramps[0], tmp_path / "b", 2.0, eeprom=eeprom, rx_at=[(1.0, "ID\n"), (1.5, "?\n")]
    )
    comments = [raw.decode() for raw in lines if raw.startswith(b"#")]
    assert parse_banner(comments[0]).unit_id == "est-042"
    assert comments[1] == "#id unit= saved" and parse_banner(comments[2]).unit_id is None


def test_a_stuck_channel_is_named_while_the_others_move(
    built: Built, ramps: tuple[Path, np.ndarray, np.ndarray], tmp_path: Path
) -> None:
    # given: fsr2's pin stuck at 2.5 V from 5 s to 12 s
    faults = bd.BoardFaults(stuck=(bd.Stuck(1, 5.0, 12.0, 2500),))
    _, lines, instants = run(built, ramps[0], tmp_path, 15.0, faults=faults)
    got = samples(lines)
    stuck = [s.counts[1] for at, s in zip(instants, got, strict=True) if 5.01 < at < 11.99]
    assert set(stuck) == {511}  # 2500 mV of 5000 at 10 bits
    # when: the host's health reads the stream
    health = StreamHealth(rate_hz=30.0)
    health.connected(0.0, settle_s=0.0)
    flagged = []
    for at, s in zip(instants, got, strict=True):
        health.channels(at, s.millis / 1000, s.counts, 1023, NAMES)
        if "stuck" in health.problems(at):
            flagged.append(at)
    # then: flagged from 2 s after it stuck until the hold after it came free, naming the channel, once
    assert 6.9 < flagged[0] < 7.2 and 12.0 < flagged[-1] < 14.1
    assert health.counts["stuck_channels"] == 1
    assert "fsr2 stuck at" in health.problems(flagged[0])["stuck"]


def test_emulate_board_says_how_to_build_what_is_missing_and_refuses_a_bad_fault(tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from pipeline.cli import app
    from tests.live.conftest import write_trials

    trial = str(write_trials(tmp_path / "held", [30], adc_bits=10)[0])
    link = ["--link", str(tmp_path / "board")]
    # given: no firmware built there; then: the error names it and the command that builds it
    missing = CliRunner().invoke(app, ["emulate-board", trial, *link, "--elf", str(tmp_path / "none.elf")])
    assert missing.exit_code == 1 and "none.elf" in missing.output and "make firmware" in missing.output
    # given: a stuck channel written wrong
    bad = CliRunner().invoke(app, ["emulate-board", trial, *link, "--stuck", "1:5:2500"])
    assert bad.exit_code == 1 and "PIN:FROM_S:TO_S:MV, not '1:5:2500'" in bad.output
