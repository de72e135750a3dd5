"""The emulated board: the shipped firmware (`firmware/`) on simavr's ATmega328P, its analog pins driven
from rig-log/1 trials, its UART on a pseudo-terminal (docs/live.md, "The emulated board").

`emulate` plays files as the Python emulator's `play` does, but the lines come from the firmware: its
banner, its sample clock, its 10-bit conversions, its serial buffer. The harness itself is C
(`firmware/board/board.c`, built by `make firmware`); this module writes its table of pin voltages,
starts it and reads what it measured. The clock figures are small functions of the sample instants.
"""

from __future__ import annotations

import json
import math
import subprocess
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.live.emulate import Trial, schedule
from pipeline.live.wire import RATE_HZ

FIRMWARE = Path(__file__).resolve().parents[2] / "firmware"  # the repository's firmware folder
BUILD = FIRMWARE / "build"
VCC_MV = 5000  # the Uno's supply, which is the ADC's reference (AVCC)
BOOT_MS = 200.0  # the emulated board starts this long after power-on or a reset (a real Uno: ~0.5-1.5 s)
# The share of the previous pin's voltage the first conversion after a multiplexer switch reads: an FSR
# divider of tens of kilo-ohms does not recharge the ADC's sample-and-hold capacitor in one conversion.
# A model, not a measurement: the firmware's discarded conversion must make it harmless at any share.
CROSSTALK = 0.2


@dataclass(frozen=True)
class Stuck:
    """Pin `pin` reads `mv` millivolts from `from_s` to `to_s` (board seconds): a stuck channel."""

    pin: int
    from_s: float
    to_s: float
    mv: int

    def arg(self) -> str:
        return f"{self.pin}:{self.from_s:g}:{self.to_s:g}:{self.mv}"

    @classmethod
    def parse(cls, text: str) -> Stuck:
        try:
            pin, a, b, mv = text.split(":")
            return cls(int(pin), float(a), float(b), int(mv))
        except ValueError:
            raise ValueError(f"a stuck channel is PIN:FROM_S:TO_S:MV, not {text!r}") from None


@dataclass(frozen=True)
class BoardFaults:
    reset_at_s: tuple[float, ...] = ()  # resets (board seconds)
    stuck: tuple[Stuck, ...] = ()
    freq_hz: int = 16_000_000  # the crystal; the firmware assumes 16 MHz (a slow one: 15_920_000)
    dev_buf: int = 4000  # bytes the USB link holds for a host that stops reading (64..4095); the rest is lost


def millivolts(counts: np.ndarray, adc_bits: int = 10, vref_v: float = 5.0) -> np.ndarray:
    """Pin voltages (mV, integers) that a 10-bit ADC on the 5 V reference reads back as the volts of
    `counts` (at `adc_bits` on `vref_v`): rounded up, so a 10-bit count comes back exactly."""
    volts = np.asarray(counts) * vref_v / (2**adc_bits - 1)
    return np.clip(np.ceil(volts * 1000 - 1e-6), 0, VCC_MV).astype(np.int64)


def write_pins(path: Path, t_s: np.ndarray, mv: np.ndarray) -> Path:
    """The harness's pin table: from board second t_s[i] on, pin k holds mv[i, k] millivolts."""
    lines = ["t_s," + ",".join(f"mv{k}" for k in range(mv.shape[1]))]
    lines += [f"{t:.6f}," + ",".join(map(str, row)) for t, row in zip(t_s, mv, strict=True)]
    path.write_text("\n".join(lines) + "\n")
    return path


def write_table(trials: Sequence[Trial], path: Path, pause_s: float, boot_ms: float = BOOT_MS) -> float:
    """The pin table for `trials` (one unit's files: the first one's ADC settings convert all) played
    as `schedule` plays them, from board power-on (the sketch starts `boot_ms` later); returns the
    board seconds the playback takes."""
    plan = schedule(trials, pause_s)
    t = np.array([at for at, _ in plan]) + boot_ms / 1000
    banner = trials[0].banner
    write_pins(
        path, t, millivolts(np.array([s.counts for _, s in plan]), banner.adc_bits, banner.vref_v or 5.0)
    )
    return float(t[-1]) + 1 / RATE_HZ


def command(
    elf: Path,
    table: Path | None,
    *,
    board: Path = BUILD / "board",
    link: Path | None = None,
    tx: Path | None = None,
    events: Path | None = None,
    seconds: float | None = None,
    faults: BoardFaults | None = None,
    boot_ms: float = BOOT_MS,
    crosstalk: float = CROSSTALK,
    eeprom: Path | None = None,
    rx_at: Sequence[tuple[float, str]] = (),
) -> list[str]:
    """The harness's command line (firmware/board/board.c says what each option does)."""
    faults = faults or BoardFaults()
    args = [str(board), "--elf", str(elf), "--boot-ms", f"{boot_ms:g}", "--crosstalk", f"{crosstalk:g}"]
    args += ["--freq", str(faults.freq_hz), "--dev-buf", str(faults.dev_buf)]
    for flag, value in (("--table", table), ("--pty", link), ("--tx", tx), ("--events", events),
                        ("--eeprom", eeprom), ("--seconds", seconds)):  # fmt: skip
        if value is not None:
            args += [flag, f"{value:g}" if isinstance(value, float) else str(value)]
    for at in faults.reset_at_s:
        args += ["--reset-at", f"{at:g}"]
    for s in faults.stuck:
        args += ["--stuck", s.arg()]
    for at, text in rx_at:
        args += ["--rx-at", f"{at:g}:" + text.replace("\n", "\\n")]
    return args


def missing_build(elf: Path, board: Path) -> str | None:
    """What is not built, and how to build it; None when both are there."""
    gone = [p for p in (elf, board) if not p.is_file()]
    if not gone:
        return None
    needs = "Debian's gcc-avr, avr-libc, arduino-core-avr and libsimavr-dev: `make setup-system`"
    return f"{', '.join(map(str, gone))} not built: run `make firmware` (it needs {needs})"


def summary(stdout: str) -> dict[str, float]:
    """The harness's closing JSON line."""
    for line in reversed(stdout.splitlines()):
        if line.startswith("{"):
            return json.loads(line)
    raise ValueError(f"the board printed no summary: {stdout[-300:]!r}")


def run(args: list[str], timeout_s: float) -> dict[str, float]:
    """Run the harness to its end (`--seconds`); its summary. Raises naming its exit and stderr."""
    done = subprocess.run(args, capture_output=True, text=True, timeout=timeout_s)
    if done.returncode != 0:
        raise RuntimeError(f"board exited {done.returncode}: {done.stderr.strip() or done.stdout[-300:]}")
    return summary(done.stdout)


def sample_instants(events: Path) -> np.ndarray:
    """Board seconds of every sample the firmware took (its first conversion of pin 0)."""
    ns = [int(line.split()[1]) for line in events.read_text().splitlines() if line.startswith("S ")]
    return np.array(ns, dtype=np.float64) / 1e9


@dataclass(frozen=True)
class ClockFigures:
    samples: int
    rate_hz: float
    rate_error: float  # relative to the declared rate
    jitter: float  # the largest deviation of one period from the mean period, as a share of it
    drift: float  # the largest deviation of an instant from the straight line through all, as a share


def clock_figures(instants: np.ndarray, declared_hz: float) -> ClockFigures:
    """How well a sample clock keeps time, from its sample instants (seconds)."""
    if len(instants) < 3:
        raise ValueError(f"{len(instants)} sample instants: too few to judge a clock")
    periods = np.diff(instants)
    mean = float(periods.mean())
    k = np.arange(len(instants))
    slope, icpt = np.polyfit(k, instants, 1)
    return ClockFigures(
        samples=len(instants),
        rate_hz=1 / mean,
        rate_error=(1 / mean - declared_hz) / declared_hz,
        jitter=float(np.abs(periods - mean).max() / mean),
        drift=float(np.abs(instants - (slope * k + icpt)).max() / mean),
    )


def emulate(
    trials: Sequence[Trial],
    link: Path,
    table: Path,
    *,
    elf: Path = BUILD / "needlecue.elf",
    board: Path = BUILD / "board",
    pause_s: float = 3.0,
    seconds: float | None = None,
    faults: BoardFaults | None = None,
    eeprom: Path | None = None,
    wait_reader_s: float = 60.0,
) -> subprocess.Popen[str]:
    """Start the emulated board playing `trials` (its pin voltages written to `table`) on a
    pseudo-terminal at `link`, at the real rate; it powers on when a reader opens the port and stops
    `seconds` later (default: 1 s after the last rest). The caller waits for it (its summary is the
    last line of its output)."""
    if problem := missing_build(elf, board):
        raise FileNotFoundError(problem)
    length = write_table(trials, table, pause_s)
    args = command(elf, table, board=board, link=link, seconds=seconds or math.ceil(length + 1),
                   faults=faults, eeprom=eeprom)  # fmt: skip
    args += ["--wait-reader", f"{wait_reader_s:g}"]
    return subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
