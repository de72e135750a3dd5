"""The serial stream's health, judged line by line: rate, gaps, late samples, garbage, a wrong baud
rate, silence, a pulled cable and a stuck channel. Each problem stays on show for `HOLD_S` after it was
last seen, so a trainee has time to read it; `counts` keeps the session's totals for the recording."""

from __future__ import annotations

from collections import Counter, deque
from dataclasses import dataclass, field

import numpy as np

from pipeline.live.wire import BAUD

HOLD_S = 2.0  # a problem stays on the display this long after it was last seen
GAP_FRAMES = 2.5  # a jump of the board's clock longer than this many frames is a gap
LATE_S = 0.1  # a sample arriving this much later than its board time says (3 frames) is late
SILENT_S = 0.3  # no sample for this long (9 frames) is silence
RATE_TOL = 0.1  # the measured rate may be this far (relative) off the nominal one
RATE_WINDOW = 60  # samples the rate is measured over (2 s)
BAUD_WINDOW_S = 2.0  # a window with only garbage in it: the baud rate is probably wrong
DRIFT = 0.01  # the board's clock may run this much (relative) slower than the host's
STUCK_S = 2.0  # a channel whose count has not changed for this long (board time) ...
STUCK_MOVE = 0.02  # ... while another moved this share of full scale (20 counts at 10 bits) ...
STUCK_CHANGES = 10  # ... in at least this many steps (one jump is a fault or a bump, not a load) is stuck


@dataclass
class StreamHealth:
    """Feed it every line's fate (`sample`, `garbage`) and the clock (`tick`); `problems` says what is
    wrong now, as {key: message} in a stable order."""

    rate_hz: float
    baud: int = BAUD
    counts: Counter[str] = field(default_factory=Counter)
    _seen: dict[str, tuple[float, str]] = field(default_factory=dict)  # key -> (last seen, message)
    _millis: deque[float] = field(default_factory=lambda: deque(maxlen=RATE_WINDOW))
    _garbage: deque[float] = field(default_factory=deque)
    _offset: float | None = None  # min over the session of host time - board time
    _last_sample_host: float | None = None
    _connected_at: float | None = None
    _quiet_until: float = 0.0
    _disconnected: str | None = None
    _window: deque[tuple[float, tuple[int, ...]]] = field(default_factory=deque)  # the last STUCK_S
    _stuck: set[int] = field(default_factory=set)

    def _flag(self, now: float, key: str, message: str) -> None:
        self._seen[key] = (now, message)

    def connected(self, now: float, settle_s: float) -> None:
        """The port is open; silence is expected while the board resets (`settle_s`)."""
        self._disconnected = None
        self._seen.pop("disconnected", None)
        self._connected_at = now
        self._quiet_until = now + settle_s
        self._last_sample_host = None
        self._millis.clear()
        self._window.clear()

    def disconnected(self, now: float, why: str) -> None:
        self.counts["disconnects"] += 1
        self._disconnected = why
        self._flag(now, "disconnected", f"estimator disconnected ({why}): cable pulled? reconnecting")

    def sample(self, now: float, board_s: float, gap_s: float | None) -> None:
        """A valid sample arrived at host time `now` with board time `board_s`; `gap_s` is the board
        time since the previous sample (None for the first after a connect)."""
        self.counts["samples"] += 1
        self._last_sample_host = now
        self._millis.append(board_s)
        frame = 1.0 / self.rate_hz
        if gap_s is not None and gap_s > GAP_FRAMES * frame:
            lost = round(gap_s * self.rate_hz) - 1
            self.counts["gaps"] += 1
            self.counts["lost_samples"] += lost
            self._flag(now, "gap", f"gap in the stream: {lost} sample(s) lost ({gap_s * 1000:.0f} ms)")
        # how late a sample is: its host-minus-board offset above the least offset seen. The board's
        # clock (a ceramic resonator on an Uno: up to 0.5 % off) drifts against the host's, so the
        # least offset may rise by DRIFT of the time that passed; a stall's burst rises far faster.
        offset = now - board_s
        if self._offset is None or gap_s is None:
            self._offset = offset
        else:
            self._offset = min(offset, self._offset + DRIFT * gap_s)
        late = offset - self._offset
        if late > LATE_S:
            self.counts["late_samples"] += 1
            self._flag(now, "late", f"late samples: arrived up to {late * 1000:.0f} ms after they were read")
        if len(self._millis) == RATE_WINDOW:
            span = self._millis[-1] - self._millis[0]
            rate = (len(self._millis) - 1) / span if span > 0 else float("inf")
            if abs(rate - self.rate_hz) > RATE_TOL * self.rate_hz:
                self._flag(now, "rate", f"sample rate {rate:.1f} Hz, expected {self.rate_hz:g} Hz")

    def channels(
        self, now: float, board_s: float, counts: tuple[int, ...], adc_max: int, names: tuple[str, ...]
    ) -> None:
        """A sample's counts: a channel that has not changed by one count for `STUCK_S` while another
        moved is stuck (a broken wire, an ADC channel that stopped). A live force-sensing resistor never
        holds one count exactly while the silicone around it is loaded. A channel at 0 or full scale
        is left alone: an unloaded FSR over a pull-down reads 0 and a saturated one full scale, as a
        broken wire may (the two cannot be told apart)."""
        window = self._window
        window.append((board_s, counts))
        while window[0][0] < board_s - STUCK_S:
            window.popleft()
        if (
            board_s - window[0][0] < STUCK_S - 1.5 / self.rate_hz
            or len(window) < 0.9 * STUCK_S * self.rate_hz
        ):
            return  # not 2 s yet, or samples lost in them: a channel seen a few times may seem still
        table = np.array([c for _, c in window])
        span = table.max(axis=0) - table.min(axis=0)
        steps = (np.diff(table, axis=0) != 0).sum(axis=0)
        moved = (span >= STUCK_MOVE * adc_max) & (steps >= STUCK_CHANGES)
        for k in range(len(counts)):
            if span[k] > 0 or not 0 < counts[k] < adc_max:  # at a rail: an unloaded or saturated FSR
                self._stuck.discard(k)
            elif np.delete(moved, k).any():
                if k not in self._stuck:
                    self._stuck.add(k)
                    self.counts["stuck_channels"] += 1
                name = names[k] if k < len(names) else f"channel {k + 1}"
                self._flag(
                    now,
                    "stuck",
                    f"{name} stuck at {counts[k]} for {STUCK_S:g} s while the others moved: "
                    "a broken wire or a dead channel? The force and cue are wrong",
                )

    def garbage(self, now: float, why: str) -> None:
        self.counts["garbage_lines"] += 1
        self._garbage.append(now)
        self._flag(now, "garbage", f"garbled line(s) ignored ({why})")

    def problems(self, now: float) -> dict[str, str]:
        """What is wrong at host time `now`."""
        while self._garbage and self._garbage[0] < now - BAUD_WINDOW_S:
            self._garbage.popleft()
        out: dict[str, str] = {}
        if self._disconnected is not None:
            out["disconnected"] = self._seen["disconnected"][1]
            return out
        recent_sample = self._last_sample_host is not None and now - self._last_sample_host < BAUD_WINDOW_S
        if len(self._garbage) >= 5 and not recent_sample:
            out["baud"] = (
                f"nothing readable, {len(self._garbage)} garbled line(s) in {BAUD_WINDOW_S:g} s: "
                f"is the port's baud rate ({self.baud}) the firmware's? (--baud)"
            )
        if now >= self._quiet_until:
            since = self._last_sample_host if self._last_sample_host is not None else self._connected_at
            if since is not None and now - since > SILENT_S:
                out["silent"] = f"no samples for {now - since:.1f} s: cable pulled or estimator stopped?"
        for key, (seen, message) in self._seen.items():
            if key not in out and now - seen <= HOLD_S and key != "disconnected":
                out[key] = message
        return out
