"""Running a session: live from a serial port with the displays and a recording (`run_live`), or
again from a recording (`replay_session`), which feeds the recorded lines through the same chain."""

from __future__ import annotations

import signal
import time
from collections.abc import Callable
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any

from needlecue_client.force import ForceClient
from pipeline.live.display import Board, TerminalView, WebDisplay
from pipeline.live.port import run_port
from pipeline.live.recording import SessionRecorder, read_lines, read_meta, unescape
from pipeline.live.session import LiveSession, StreamSettings
from pipeline.live.wire import BAUD, WIRE


@dataclass(frozen=True)
class LiveOptions:
    port: str
    baud: int = BAUD
    adc_bits: int | None = None  # None: the banner's, else 10
    vref_v: float | None = None  # None: the banner's, else 5.0
    record_root: Path = Path("recordings")
    session_dir: Path | None = None  # None: <record_root>/live-<date>-<time>
    http_host: str = "127.0.0.1"
    http_port: int = 8770  # 0: any free port
    reset_wait_s: float = 2.0
    insertions: int | None = None  # stop after this many insertions have ended
    duration_s: float | None = None
    give_up_s: float | None = None  # stop when the port has been gone this long


def settings_for(client: ForceClient, options: LiveOptions) -> tuple[StreamSettings, frozenset[str]]:
    fixed = frozenset(k for k in ("adc_bits", "vref_v") if getattr(options, k) is not None)
    return (
        StreamSettings(
            channels=tuple(client.channels),
            adc_bits=10 if options.adc_bits is None else options.adc_bits,
            vref_v=5.0 if options.vref_v is None else options.vref_v,
            rate_hz=float(client.rate_hz or 30.0),
            baud=options.baud,
        ),
        fixed,
    )


def run_live(
    client: ForceClient,
    options: LiveOptions,
    say: Callable[[str], None] = print,
    cues_uncalibrated: bool = False,
) -> dict[str, Any]:
    """The live session: port -> session -> web page, terminal line and recording, until Ctrl-C,
    `insertions` ended, `duration_s` passed or the port gone for `give_up_s`. Returns its summary."""
    settings, fixed = settings_for(client, options)
    folder = options.session_dir or options.record_root / datetime.now().strftime("live-%Y%m%d-%H%M%S")
    board = Board(client.standard_profile)
    web = WebDisplay(board, options.http_host, options.http_port)  # a busy port fails before a recording
    recorder = SessionRecorder(
        folder,
        {
            "sensor": {
                "unit_id": client.unit_id or "unknown",
                "channels": list(settings.channels),
                "units": "counts",
                "adc_bits": settings.adc_bits,
                "vref_v": settings.vref_v,
            },
            "reference": {"units": "N", "model": "none: a live session has no reference stream"},
            "live": {
                "wire": WIRE,
                "port": options.port,
                "baud": options.baud,
                "model": client.name,
                "preset_angle_deg": client.angle_deg,
                "calibrated": client.calibrated,
                "calibration": client.calibration,
                # what replay needs to read the lines as live did: the settings given, not the banner's
                "given": {"adc_bits": options.adc_bits, "vref_v": options.vref_v},
                "cues_uncalibrated": cues_uncalibrated,
            },
        },
        settings.channels,
        targets=client.targets,
    )
    web.start()
    term = TerminalView()

    def publish(state: dict[str, Any]) -> None:
        board.publish(state)
        term.publish(state)

    session = LiveSession(client, settings, recorder=recorder, publish=publish, fixed=fixed)
    say(f"display: {web.url}")
    say(f"recording: {folder}")
    if not client.calibrated:
        say(f"uncalibrated unit: {client.uncalibrated_reason}; force only, no cues")
    stop = {"signal": False}
    started = time.monotonic()

    def should_stop() -> bool:
        ended = sum(1 for i in session.insertions if i.ended is not None)
        return (
            stop["signal"]
            or (options.insertions is not None and ended >= options.insertions)
            or (options.duration_s is not None and time.monotonic() - started >= options.duration_s)
        )

    def on_signal(_sig: int, _frame: Any) -> None:
        stop["signal"] = True

    old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        why = run_port(
            session,
            options.port,
            options.baud,
            reset_wait_s=options.reset_wait_s,
            should_stop=should_stop,
            give_up_s=options.give_up_s,
            say=lambda m: say(f"\n{m}" if term.tty else m),
        )
    finally:
        for s, handler in old.items():
            signal.signal(s, handler)
        try:
            summary = session.close(time.time())
        finally:
            web.stop()
    summary["stopped"] = why
    summary["recording"] = str(folder)
    return summary


def replay_session(folder: Path, client: ForceClient) -> dict[str, Any]:
    """A recorded session's lines through the same chain as live (no displays, no new recording)."""
    given = (read_meta(folder).get("live") or {}).get("given") or {}
    options = LiveOptions(port="", adc_bits=given.get("adc_bits"), vref_v=given.get("vref_v"))
    settings, fixed = settings_for(client, options)  # as live started; the banner changes them as it did
    session = LiveSession(client, settings, fixed=fixed)
    last = 0.0
    for host_s, kind, text in read_lines(folder):
        last = host_s
        if kind == "line":
            session.line(host_s, unescape(text))
        elif kind == "connect":
            port, _, settle = text.rpartition(" settle_s=")
            session.connected(host_s, port, float(settle or 0))
        elif kind == "disconnect":
            session.disconnected(host_s, text)
        elif kind == "partial":
            session.partial(host_s, unescape(text))
        else:
            raise ValueError(f"{folder}: unknown line kind {kind!r} in the recording")
    return session.close(last)
