"""The serial port: open it, wait out the board's reset, cut the byte stream into lines stamped with
the host's clock, and survive a pulled cable (reopen until the port is back).

`run_port` drives a `LiveSession` until `should_stop()` says so; nothing here knows about models.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable
from typing import Any

from pipeline.live.session import LiveSession
from pipeline.live.wire import MAX_LINE

READ_TIMEOUT_S = 0.02  # the longest a read blocks: how often silence and faults are looked at
REOPEN_EVERY_S = 0.5


def open_serial(port: str, baud: int) -> Any:
    """The port opened with pyserial at `baud`, 8N1, no flow control."""
    import serial  # pyserial, imported here so that the rest of needlecue does not need it

    return serial.Serial(port, baudrate=baud, timeout=READ_TIMEOUT_S)


def run_port(
    session: LiveSession,
    port: str,
    baud: int,
    *,
    reset_wait_s: float = 2.0,
    should_stop: Callable[[], bool] = lambda: False,
    give_up_s: float | None = None,
    say: Callable[[str], None] = lambda _m: None,
    opener: Callable[[str, int], Any] = open_serial,
) -> str:
    """Read `port` into `session` until `should_stop()`; returns why it stopped. A port that cannot be
    opened, or goes away, is retried every REOPEN_EVERY_S; after `give_up_s` without it, it stops."""
    import serial

    ser = None
    lost_since: float | None = time.monotonic()
    first_error: str | None = None
    buf = b""
    drop_first = True
    try:
        while not should_stop():
            if ser is None:
                try:
                    ser = opener(port, baud)
                except (serial.SerialException, OSError) as e:
                    first_error = first_error or str(e)
                    gone = 0.0 if lost_since is None else time.monotonic() - lost_since
                    if give_up_s is not None and gone > give_up_s:
                        return f"gave up on {port} after {give_up_s:g} s: {first_error}"
                    session.tick(time.time())
                    time.sleep(REOPEN_EVERY_S)
                    continue
                # an Arduino resets when the port opens (DTR): its bootloader runs, then the sketch starts
                # over, printing its banner. Until reset_wait_s has passed, silence is no fault.
                session.connected(time.time(), port, reset_wait_s)
                say(f"connected to {port} at {baud} baud")
                buf, drop_first, lost_since, first_error = b"", True, None, None
            try:
                chunk = ser.read(ser.in_waiting or 1)
            except (serial.SerialException, OSError) as e:
                why = str(e).split(":")[0] if str(e) else type(e).__name__
                session.disconnected(time.time(), why)
                say(f"lost {port}: {e}")
                _close(ser)
                ser, lost_since = None, time.monotonic()
                continue
            now = time.time()
            if not chunk:
                session.tick(now)
                continue
            buf += chunk
            *lines, buf = buf.split(b"\n")
            for raw in lines:
                raw = raw.rstrip(b"\r")
                if drop_first:  # the port may open mid-line: the first fragment is not a whole line,
                    drop_first = False  # unless it is the banner a freshly reset board starts with
                    if not raw.startswith(b"#"):
                        session.partial(now, raw)
                        continue
                session.line(time.time(), raw)
            if len(buf) > MAX_LINE:  # no line break for too long: garbage, not a line in the making
                session.line(now, buf)
                buf = b""
        return "stopped"
    finally:
        if ser is not None:
            _close(ser)


def _close(ser: Any) -> None:
    with contextlib.suppress(Exception):  # a port that vanished may fail to close: it is gone anyway
        ser.close()
