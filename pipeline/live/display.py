"""The trainee's displays: a local web page (Server-Sent Events, one state per frame) and a compact
terminal line. Both take the session's states through `publish`.

The page (`page.html`) shows the cue large and colour-coded, the reason, the estimated angle, the
predicted force against the preset angle's standard profile, the stream's problems and the last
insertions' cue sequences. `/state` answers the newest state as JSON, `/profile` the profile.
"""

from __future__ import annotations

import json
import shutil
import sys
import threading
import time
from collections import deque
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from typing import IO, Any

from needlecue_runtime.cues.pack import NO_CUE_REASONS
from needlecue_runtime.vocab import AXES

KEEPALIVE_S = 5.0


class Board:
    """The newest state, and a condition the page connections wait on."""

    def __init__(self, profile: dict[str, Any] | None) -> None:
        self.profile = profile
        self.state: dict[str, Any] = {}
        self.cond = threading.Condition()
        # (seq, DOM updated, painted) in epoch seconds, posted by a page opened with ?bench=1
        self.renders: deque[tuple[int, float, float]] = deque(maxlen=100_000)
        self.written: deque[tuple[int, float]] = deque(maxlen=100_000)  # (seq, sent to a page) epoch s
        self.closed = False
        self.streams = 0  # pages connected to /events

    def publish(self, state: dict[str, Any]) -> None:
        with self.cond:
            self.state = state
            self.cond.notify_all()

    def close(self) -> None:
        with self.cond:
            self.closed = True
            self.cond.notify_all()


def _handler(board: Board) -> type[BaseHTTPRequestHandler]:
    page = resources.files("pipeline.live").joinpath("page.html").read_bytes()

    class Handler(BaseHTTPRequestHandler):
        protocol_version = "HTTP/1.1"
        disable_nagle_algorithm = True  # a frame's state is one small write: send it now, not with the next

        def log_message(self, format: str, *args: Any) -> None:  # quiet: the terminal is the trainee's
            pass

        def _send(self, body: bytes, ctype: str, code: int = 200) -> None:
            self.send_response(code)
            self.send_header("Content-Type", ctype)
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Cache-Control", "no-store")
            self.end_headers()
            self.wfile.write(body)

        def do_GET(self) -> None:
            path = self.path.split("?", 1)[0]
            if path == "/":
                self._send(page, "text/html; charset=utf-8")
            elif path == "/state":
                with board.cond:
                    body = json.dumps(board.state).encode()
                self._send(body, "application/json")
            elif path == "/profile":
                self._send(json.dumps(board.profile).encode(), "application/json")
            elif path == "/events":
                self._events()
            else:
                self._send(b"not found\n", "text/plain", 404)

        def do_POST(self) -> None:
            try:
                n = min(max(int(self.headers.get("Content-Length") or 0), 0), 1 << 22)
            except ValueError:
                n = 0
            body = self.rfile.read(n)  # always read, so a kept-alive connection stays in step
            if self.path != "/bench":
                self._send(b"not found\n", "text/plain", 404)
                return
            try:
                rows = [(int(s), float(a) / 1000, float(b) / 1000) for s, a, b in json.loads(body)]
            except (ValueError, TypeError):
                self._send(b"bad rows\n", "text/plain", 400)
                return
            with board.cond:
                board.renders.extend(rows)
            self._send(b"ok\n", "text/plain")

        def _events(self) -> None:
            self.send_response(200)
            self.send_header("Content-Type", "text/event-stream")
            self.send_header("Cache-Control", "no-store")
            self.send_header("Connection", "close")
            self.end_headers()
            sent = -1
            with board.cond:
                board.streams += 1
            try:
                while True:
                    last = sent
                    with board.cond:
                        board.cond.wait_for(
                            lambda last=last: board.closed or board.state.get("seq", -1) != last, KEEPALIVE_S
                        )
                        state, closed = board.state, board.closed
                    if closed and state.get("seq", -1) == sent:
                        return  # the session is over and the page has its last state
                    if state.get("seq", -1) == sent:
                        self.wfile.write(b": keepalive\n\n")
                    else:
                        sent = state["seq"]
                        self.wfile.write(b"data: " + json.dumps(state).encode() + b"\n\n")
                        board.written.append((sent, time.time()))
                    self.wfile.flush()
            except OSError:
                return  # the page closed (or its connection broke)
            finally:
                with board.cond:
                    board.streams -= 1
                    board.cond.notify_all()

    return Handler


class WebDisplay:
    """The page's HTTP server on 127.0.0.1, in a thread of its own."""

    def __init__(self, board: Board, host: str = "127.0.0.1", port: int = 8770) -> None:
        self.board = board
        self.server = ThreadingHTTPServer((host, port), _handler(board))
        self.server.daemon_threads = True
        self._thread = threading.Thread(target=self.server.serve_forever, name="live-display", daemon=True)

    @property
    def url(self) -> str:
        host, port = self.server.server_address[:2]
        return f"http://{host}:{port}/"

    def start(self) -> WebDisplay:
        self._thread.start()
        return self

    def stop(self, drain_s: float = 1.0) -> None:
        """Stop serving; the open pages first get the session's last state (for up to `drain_s`)."""
        board = self.board
        board.close()
        with board.cond:
            board.cond.wait_for(lambda: board.streams == 0, drain_s)
        self.server.shutdown()
        self.server.server_close()


CUE_WORDS = {
    "continue": "CONTINUE",
    "correct": "CORRECT ANGLE",
    "stop": "STOP",
    "wait": "wait",
    "none": "no angle cue",
}


def _force_text(force: list[float] | None, targets: list[str] | None) -> str:
    """` F=(+0.10, -0.20, +1.50) N` for the three axes; the axes named when the model gives fewer
    (` fz=+1.50 N`: only what the reference recorded)."""
    if not force:
        return ""
    if targets is None or list(targets) == list(AXES):
        return " F=(" + ", ".join(f"{v:+.2f}" for v in force) + ") N"
    return " " + " ".join(f"{a}={v:+.2f}" for a, v in zip(targets, force, strict=True)) + " N"


def terminal_line(state: dict[str, Any]) -> str:
    """The compact terminal view of one state."""
    cue = CUE_WORDS.get(state.get("cue", ""), state.get("cue", ""))
    if state.get("cue") == "none" and state.get("no_cue") in NO_CUE_REASONS:
        cue += f" ({NO_CUE_REASONS[state['no_cue']]})"
    ins = state.get("insertion")
    head = f"[{state.get('preset_angle_deg', 0):g}°] " + (f"#{ins} " if ins else "rest ")
    est = state.get("angle_est_deg")
    angle = f" angle {est:.0f}°" if est is not None else ""
    force = _force_text(state.get("force_n"), state.get("targets"))
    unit = "" if state.get("calibrated") else " [uncalibrated unit]"
    problems = "; ".join((state.get("problems") or {}).values())
    return f"{head}{cue:<13}{angle}{force}{unit}" + (f"  ! {problems}" if problems else "")


class TerminalView:
    """On a terminal, one line rewritten in place (at most `max_hz`); otherwise a line per change."""

    def __init__(self, out: IO[str] | None = None, max_hz: float = 10.0) -> None:
        self.out = out or sys.stdout
        self.tty = self.out.isatty()
        self._every = 1.0 / max_hz
        self._next = 0.0
        self._last_key: tuple = ()

    def publish(self, state: dict[str, Any]) -> None:
        if self.tty:
            now = time.monotonic()
            if now < self._next:
                return
            self._next = now + self._every
            width = shutil.get_terminal_size((100, 20)).columns - 1
            self.out.write("\r" + terminal_line(state)[:width].ljust(width))
            self.out.flush()
            return
        key = (
            state.get("phase"),
            state.get("insertion"),
            state.get("cue"),
            tuple(state.get("problems") or {}),
        )
        if key != self._last_key:
            self._last_key = key
            self.out.write(f"{state.get('t_s', 0.0):8.2f} s  {terminal_line(state)}\n")
            self.out.flush()
