"""`needlecue emulate-rig`: the estimator's firmware played over a pseudo-terminal, so the whole live
chain runs without hardware (docs/live.md, "Emulating the rig").

Trials are rig-log/1 estimator files (`<trial>.fsr.csv`, or `.csv.gz`: simulated by `needlecue
simulate-batch` / the pipeline, or recorded by a lab), sent line by line in the wire format at their
recorded times. Like an Arduino Uno, the emulated board starts (banner, then samples) when a reader
opens the port. Between trials, and before the first and after the last, the needle rests: the next
trial's first reading repeats at the stream's rate for `pause_s`.

Faults, for tests and demonstrations: the cable pulled (the pty closes; `replug_after_s` later a new
one appears under the same link and the board starts over), garbage bytes, a stall that delivers a
burst of late samples, and a baud rate other than the reader's (what the reader gets is garbled, as a
UART at the wrong rate would read it).
"""

from __future__ import annotations

import contextlib
import os
import pty
import termios
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pipeline.live.wire import BAUD, RATE_HZ, Banner, Sample, format_banner, format_sample

BOOT_MILLIS = 1500  # an Uno's sketch starts about 1.5 s after the reset: its millis() then
BOOT_S = 0.2  # the emulated board starts this long after the port opens (a real one: about 1.5 s)


@dataclass(frozen=True)
class Trial:
    name: str
    t_ms: np.ndarray  # recorded times, ms
    counts: np.ndarray  # (n, channels) ADC counts
    banner: Banner


@dataclass(frozen=True)
class Faults:
    pull_at_s: float | None = None
    replug_after_s: float | None = None
    garbage_at_s: tuple[float, ...] = ()
    stall_at_s: float | None = None
    stall_s: float = 0.5
    baud: int = BAUD  # the rate the emulated firmware sends at


def load_trial(path: Path, adc_bits: int = 10, vref_v: float = 5.0) -> Trial:
    """A rig-log/1 estimator file and its batch.yaml; ValueError saying file, line and column."""
    from pipeline.rig.batch_yaml import read_meta
    from pipeline.rig.csvfile import read_csv
    from pipeline.rig.problems import ProblemLog

    probs = ProblemLog(path.parent.name)
    meta = read_meta(path.parent, probs)
    table = read_csv(path, probs, None) if meta is not None else None
    if meta is None or table is None:
        raise ValueError("; ".join(f"{p.file}: {p.reason}" for p in probs.finish()) or f"{path}: unreadable")
    s = meta.sensor
    missing = [c for c in ("t_ms", *s.channels) if c not in table.header]
    if missing:
        raise ValueError(f"{path}:{table.header_line}: no column(s) {missing} (header {table.header})")
    cols = [table.header.index(c) for c in ("t_ms", *s.channels)]
    values = np.empty((len(table.rows), len(cols)))
    for i, (row, line) in enumerate(zip(table.rows, table.lines, strict=True)):
        for j, c in enumerate(cols):
            try:
                values[i, j] = float(row[c])
            except (ValueError, IndexError) as e:
                name = table.header[c]
                raise ValueError(f"{path}:{line} column {name!r}: not a number ({e})") from None
    if len(values) < 2 or not np.all(np.diff(values[:, 0]) > 0):
        raise ValueError(f"{path}: t_ms must strictly increase over at least two rows")
    bits, vref = (s.adc_bits, s.vref_v) if s.units == "counts" else (adc_bits, vref_v)
    raw = values[:, 1:]
    counts = raw if s.units == "counts" else raw / vref * (2**bits - 1)
    counts = np.clip(np.rint(counts), 0, 2**bits - 1).astype(np.int64)
    banner = Banner(s.unit_id, tuple(s.channels), bits, float(vref), RATE_HZ)
    return Trial(f"{path.parent.name}/{path.name}", values[:, 0], counts, banner)


def schedule(trials: Sequence[Trial], pause_s: float, rate_hz: float = RATE_HZ) -> list[tuple[float, Sample]]:
    """(seconds from the board's start, sample) of the whole playback, rests included."""
    out: list[tuple[float, Sample]] = []
    t = 0.0
    step = 1.0 / rate_hz

    def rest(reading: np.ndarray, seconds: float) -> None:
        nonlocal t
        for _ in range(round(seconds * rate_hz)):
            out.append((t, Sample(BOOT_MILLIS + round(t * 1000), tuple(int(c) for c in reading))))
            t += step

    for trial in trials:
        rest(trial.counts[0], pause_s)
        t0 = trial.t_ms[0]
        start = t
        for ms, row in zip(trial.t_ms, trial.counts, strict=True):
            t = start + (ms - t0) / 1000.0
            out.append((t, Sample(BOOT_MILLIS + round(t * 1000), tuple(int(c) for c in row))))
        t += step
    if trials:  # after the last insertion the needle rests again, as it did before it
        rest(trials[-1].counts[0], pause_s)
    return out


def garble(data: bytes, rng: np.random.Generator) -> bytes:
    """What a UART at the wrong baud rate makes of `data`: framing errors, bytes with the high bit set,
    and almost no line breaks."""
    out = rng.integers(0x80, 0x100, size=len(data), dtype=np.uint8)
    out[rng.random(len(data)) < 0.01] = ord("\n")
    return out.tobytes()


_SPEEDS = {
    getattr(termios, f"B{b}"): b
    for b in (9600, 19200, 38400, 57600, 115200, 230400)
    if hasattr(termios, f"B{b}")
}


@dataclass
class Pty:
    """One pseudo-terminal pair: we write the master; the reader opens the slave (or `link` to it)."""

    link: Path | None
    master: int = -1
    slave: int = -1
    name: str = ""
    _rng: np.random.Generator = field(default_factory=lambda: np.random.default_rng(0))

    def open(self) -> Pty:
        self.master, self.slave = pty.openpty()  # a fresh tty is canonical (ICANON): no reader yet
        os.set_blocking(self.master, False)  # a reader that stops reading must not hang the board
        self.name = os.ttyname(self.slave)
        if self.link is not None:
            with contextlib.suppress(FileNotFoundError):
                self.link.unlink()
            self.link.symlink_to(self.name)
        return self

    def reader_present(self) -> bool:
        """A reader opened the port and set it up (pyserial makes it raw: ICANON off)."""
        return not termios.tcgetattr(self.slave)[3] & termios.ICANON

    def reader_baud(self) -> int | None:
        return _SPEEDS.get(termios.tcgetattr(self.slave)[5])

    def write(self, data: bytes, baud: int) -> int:
        """Send `data` as the board would; returns the bytes dropped because nobody reads (a USB CDC
        board drops what the host does not take)."""
        reader = self.reader_baud()
        if reader is not None and reader != baud:
            data = garble(data, self._rng)
        try:
            return len(data) - os.write(self.master, data)
        except BlockingIOError:
            return len(data)

    def close(self) -> None:
        for fd in (self.master, self.slave):
            with contextlib.suppress(OSError):
                os.close(fd)
        self.master = self.slave = -1
        if self.link is not None:
            with contextlib.suppress(FileNotFoundError):
                self.link.unlink()


def play(
    trials: Sequence[Trial],
    *,
    link: Path | None = None,
    pause_s: float = 3.0,
    speed: float = 1.0,
    faults: Faults | None = None,
    wait_reader_s: float = 60.0,
    say: Callable[[str], None] = print,
) -> dict[str, int]:
    """Play `trials` over a pty until done; returns counts of what was sent."""
    faults = faults or Faults()
    if not trials:
        raise ValueError("no trials to play")
    banner = format_banner(trials[0].banner)
    plan = schedule(trials, pause_s)
    port = Pty(link).open()
    sent = {"samples": 0, "garbage": 0, "pulls": 0, "stalled": 0, "dropped_bytes": 0}
    say(f"emulate-rig: {port.name}" + (f" (link {link})" if link else "") + f", {len(plan)} samples")
    try:
        if not _wait_reader(port, wait_reader_s):
            say(f"emulate-rig: nobody opened {port.name} within {wait_reader_s:g} s")
            return sent
        time.sleep(BOOT_S / speed)  # the board boots after the reset (and the reader flushes its input)
        port.write(banner, faults.baud)
        t0 = time.monotonic()
        garbage = sorted(faults.garbage_at_s)
        held: list[bytes] = []
        offset_ms = 0  # after a replug the board starts over: its millis restart
        i = 0
        while i < len(plan):
            at, sample = plan[i]
            _sleep_until(t0 + at / speed)
            if faults.pull_at_s is not None and at >= faults.pull_at_s and sent["pulls"] == 0:
                sent["pulls"] += 1
                held = []  # what the stalled USB link held is lost with the cable
                port.close()
                say(f"emulate-rig: cable pulled at {at:.1f} s")
                if faults.replug_after_s is None:
                    return sent
                time.sleep(faults.replug_after_s / speed)
                port = Pty(link).open()
                say(f"emulate-rig: plugged in again: {port.name}")
                if not _wait_reader(port, wait_reader_s):
                    return sent
                time.sleep(BOOT_S / speed)
                port.write(banner, faults.baud)
                now = (time.monotonic() - t0) * speed
                while i < len(plan) and plan[i][0] < now:  # what the board did not send while unplugged
                    i += 1
                offset_ms = plan[i][1].millis - BOOT_MILLIS if i < len(plan) else 0
                continue
            if garbage and at >= garbage[0]:
                garbage.pop(0)
                port.write(
                    bytes(np.random.default_rng(i).integers(0x80, 0x100, 24, dtype=np.uint8)) + b"\n",
                    faults.baud,
                )
                sent["garbage"] += 1
            line = format_sample(Sample(sample.millis - offset_ms, sample.counts))
            stalled = (
                faults.stall_at_s is not None and faults.stall_at_s <= at < faults.stall_at_s + faults.stall_s
            )
            if stalled:
                held.append(line)
                sent["stalled"] += 1
            else:
                if held:
                    sent["dropped_bytes"] += port.write(b"".join(held), faults.baud)
                    held = []
                sent["dropped_bytes"] += port.write(line, faults.baud)
            sent["samples"] += 1
            i += 1
        return sent
    finally:
        time.sleep(0.2)  # let the reader take the last lines before the port goes
        port.close()


def _wait_reader(port: Pty, limit_s: float) -> bool:
    end = time.monotonic() + limit_s
    while time.monotonic() < end:
        if port.reader_present():
            return True
        time.sleep(0.01)
    return False


def _sleep_until(deadline: float) -> None:
    delay = deadline - time.monotonic()
    if delay > 0:
        time.sleep(delay)
