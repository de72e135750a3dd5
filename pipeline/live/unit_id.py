"""The estimator's unit id, read and set over serial with the firmware's commands (docs/live.md,
section 9): `?` answers with the banner, `ID <unit>` keeps the id in the board's EEPROM and answers
`#id unit=<unit> saved`, `ID` alone clears it; a refused command answers `#error ...`."""

from __future__ import annotations

import re
import time
from collections.abc import Callable, Iterator
from typing import Any

from pipeline.live.wire import MAX_LINE, WIRE, Banner, parse_banner

UNIT_ID = re.compile(r"[A-Za-z0-9._-]{1,23}")  # what the firmware's EEPROM record holds


def _lines(ser: Any, limit_s: float) -> Iterator[str]:
    """The lines the board sends within `limit_s`, as text."""
    end = time.monotonic() + limit_s
    buf = b""
    while time.monotonic() < end:
        buf += ser.read(ser.in_waiting or 1)
        *lines, buf = buf.split(b"\n")
        for raw in lines:
            yield raw.decode("ascii", "replace").strip()
        buf = buf[-MAX_LINE:]  # a longer run without a line break is garbage, not a line


def _answer(ser: Any, command: str, wanted: Callable[[str], bool], timeout_s: float) -> str:
    """Send `command` and return the first line that `wanted` accepts or that is an `#error`."""
    ser.reset_input_buffer()
    ser.write(command.encode("ascii") + b"\n")
    for text in _lines(ser, timeout_s):
        if text.startswith("#error") or wanted(text):
            return text
    raise TimeoutError(f"no answer to {command!r} within {timeout_s:g} s: is this needlecue's firmware?")


def wait_for_banner(ser: Any, limit_s: float) -> bool:
    """Wait until the banner a reset board sends has arrived, at most `limit_s` (a board that does not
    reset when the port opens sends none); whether it came."""
    return any(text.startswith(f"#{WIRE}") for text in _lines(ser, limit_s))


def read_banner(ser: Any, timeout_s: float = 3.0) -> Banner:
    """The banner the board sends when asked."""
    text = _answer(ser, "?", lambda t: t.startswith(f"#{WIRE}"), timeout_s)
    if text.startswith("#error"):
        raise ValueError(f"the board refused '?': {text}")
    return parse_banner(text)


def set_unit_id(ser: Any, unit: str | None, timeout_s: float = 3.0) -> Banner:
    """Keep `unit` (None: clear it) in the board's EEPROM; returns the banner the board then sends."""
    if unit is not None and not UNIT_ID.fullmatch(unit):
        raise ValueError(f"unit id {unit!r}: 1 to 23 of A-Z a-z 0-9 . _ -")
    command = f"ID {unit}" if unit else "ID"
    text = _answer(ser, command, lambda t: t.startswith("#id "), timeout_s)
    if text.startswith("#error"):
        raise ValueError(f"the board refused {command!r}: {text}")
    banner = read_banner(ser, timeout_s)
    if banner.unit_id != unit:
        raise ValueError(f"the board answered {text!r} but its banner says unit={banner.unit_id}")
    return banner
