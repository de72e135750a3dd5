"""The firmware's sample clock on the emulated board, against the millis()-polling sketch it replaced.

Builds both sketches and the simavr harness from source into a temporary folder (`make -C firmware`),
runs each unpaced for --seconds of board time on a 16 MHz crystal (and the firmware on a 0.5 % slow
one), and prints per run: the rate from the sample instants and its error against the banner's, the
period jitter (the largest deviation of one period from the mean), the largest deviation of an instant
from the straight line through all (both as a share of the period), the rate from the board's own
millis in the lines, and how fast simavr ran (board seconds per wall second).

    python benchmarks/bench_firmware.py [--seconds 60]

Board time is counted in emulated cycles: the figures do not depend on the host's load.
"""

from __future__ import annotations

import argparse
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

from pipeline.live import board as bd
from pipeline.live.wire import Sample, parse_banner, parse_line


def ramps(path: Path, seconds: float) -> Path:
    """Three pins that change every 50 ms (the values do not matter to the clock)."""
    t = np.arange(0, seconds, 0.05)
    k = np.arange(len(t))
    counts = np.stack([100 + (k * 7) % 300, 900 - (k * 5) % 400, 500 + (k * 11) % 200], axis=1)
    return bd.write_pins(path, t, bd.millivolts(counts))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=60.0, help="board seconds per run")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench-firmware-") as tmp:
        build = Path(tmp) / "build"
        for extra in ([], ["SKETCH=millis_poll"]):
            subprocess.run(["make", "-s", "-C", str(bd.FIRMWARE), f"BUILD={build}", "hex", "board", *extra],
                           check=True, capture_output=True)  # fmt: skip
        table = ramps(Path(tmp) / "pins.csv", args.seconds)
        runs = [
            ("firmware (Timer1), 16 MHz", "needlecue", 16_000_000),
            ("firmware (Timer1), 15.92 MHz (-0.5 %)", "needlecue", 15_920_000),
            ("millis() polling, 16 MHz", "millis_poll", 16_000_000),
        ]
        print(f"{args.seconds:g} s of board time per run; the first sample (after the boot) left out")
        header = ("run", "samples", "rate Hz", "rate err", "jitter", "drift", "millis rate", "x real time")
        print("| " + " | ".join(header) + " |\n|" + "---|" * len(header))
        for name, sketch, freq in runs:
            tx, events = Path(tmp) / "tx.bin", Path(tmp) / "events.txt"
            cmd = bd.command(build / f"{sketch}.elf", table, board=build / "board", tx=tx, events=events,
                             seconds=args.seconds, faults=bd.BoardFaults(freq_hz=freq))  # fmt: skip
            start = time.perf_counter()
            bd.run(cmd, timeout_s=args.seconds * 10)
            wall = time.perf_counter() - start
            lines = tx.read_bytes().split(b"\n")[:-1]
            declared = parse_banner(lines[0].decode()).rate_hz or 30.0
            got = [s for raw in lines if isinstance(s := parse_line(raw, 3, 1023), Sample)]
            clock = bd.clock_figures(bd.sample_instants(events)[1 : len(got)], declared)
            millis_rate = (len(got) - 2) * 1000 / (got[-1].millis - got[1].millis)
            print(
                f"| {name} | {clock.samples} | {clock.rate_hz:.4f} | {clock.rate_error * 100:+.3f} % | "
                f"{clock.jitter * 100:.3f} % | {clock.drift * 100:.3f} % | {millis_rate:.4f} | "
                f"{args.seconds / wall:.1f} |"
            )


if __name__ == "__main__":
    main()
