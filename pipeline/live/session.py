"""One live session at the simulator: serial lines in, force and cues out, frame by frame.

`LiveSession` is the whole chain without the I/O: it takes what the port delivered (`connected`,
`line`, `disconnected`, `tick`), parses the wire format, checks the stream's health, converts counts
to volts with the unit's settings, finds insertions in the signal, runs the client (the champion with
the unit's calibration, and the cue tracker) and hands each frame's state to `publish` (the displays)
and to the recorder. `needlecue live` feeds it from a serial port; `needlecue replay` feeds it a
recorded session's lines, which gives the same frames.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from needlecue_client.force import ForceClient
from pipeline.live.health import StreamHealth
from pipeline.live.insertions import InsertionDetector, InsertionRules
from pipeline.live.recording import SessionRecorder, escape
from pipeline.live.wire import BAUD, MILLIS_WRAP, Banner, Sample, parse_line

RESTART_MS = 60_000  # the board's clock jumping more than this (or back) means the board restarted
PREROLL_S = 1.5  # the rest before an insertion's start that the client sees (its rest reading)
HISTORY = 8  # insertions the display lists
TICK_S = 0.25  # without samples, the displays get a state this often

Publish = Callable[[dict[str, Any]], None]


@dataclass(frozen=True)
class StreamSettings:
    """How to read the unit's counts: from the command line, else the firmware's banner, else these."""

    channels: tuple[str, ...]
    adc_bits: int = 10
    vref_v: float = 5.0
    rate_hz: float = 30.0
    baud: int = BAUD

    @property
    def adc_max(self) -> int:
        return 2**self.adc_bits - 1

    def volts(self, counts: tuple[int, ...]) -> np.ndarray:
        """ADC counts to volts, as ingest converts them (`signals.scaling.to_volts`)."""
        return np.asarray(counts, dtype=np.float64) * (self.vref_v / self.adc_max)


@dataclass
class Insertion:
    number: int
    trial_id: str
    start_s: float
    cues: list[str] = field(default_factory=list)  # the distinct cues shown, in order
    end_s: float | None = None
    ended: str | None = None  # "end", "timeout", "disconnected", "session end"

    def summary(self) -> dict[str, Any]:
        return {
            "number": self.number,
            "trial_id": self.trial_id,
            "cues": list(self.cues),
            "final_cue": self.cues[-1] if self.cues else None,
            "ended": self.ended,
        }


class LiveSession:
    """The chain from serial lines to frames; see the module docstring."""

    def __init__(
        self,
        client: ForceClient,
        settings: StreamSettings,
        *,
        recorder: SessionRecorder | None = None,
        publish: Publish | None = None,
        rules: InsertionRules | None = None,
        fixed: frozenset[str] = frozenset(),
        clock: Callable[[], float] = time.time,
    ) -> None:
        """`fixed`: the settings given on the command line, which a banner does not override."""
        if len(settings.channels) != len(client.channels):
            raise ValueError(
                f"the stream has {len(settings.channels)} channel(s) {list(settings.channels)}, "
                f"{client.name} reads {len(client.channels)}: {list(client.channels)}"
            )
        self.client = client
        self.settings = settings
        self.recorder = recorder
        self.publish = publish or (lambda _s: None)
        self.fixed = fixed
        self.clock = clock
        self.health = StreamHealth(settings.rate_hz, settings.baud)
        self.detector = InsertionDetector(settings.rate_hz, rules)
        self.insertions: list[Insertion] = []
        self.banner: Banner | None = None
        self.notes: dict[str, str] = {}  # lasting remarks: a banner that disagrees, say
        self._preroll: deque[tuple[float, np.ndarray, tuple[int, ...], float, int]] = deque(
            maxlen=max(1, round(PREROLL_S * settings.rate_hz))
        )
        self._prev_millis: int | None = None
        self._suspect: int | None = None  # a board time that jumped, until the next line confirms it
        self._t = 0.0  # board time of the last sample, s, continuous over wraps and restarts
        self._t0_host: float | None = None
        self._last_host: float | None = None
        self._seq = 0
        self._phase = "connecting"
        self._frame: Any = None
        self._current: Insertion | None = None
        self._last_state: dict[str, Any] = {}
        self._last_emit = -float("inf")

    # --- what the port delivers -------------------------------------------------------------------

    def connected(self, host_s: float, port: str, settle_s: float) -> None:
        self._record(host_s, "connect", f"{port} settle_s={settle_s:g}")
        self.health.connected(host_s, settle_s)
        self._prev_millis = None
        self.detector.reset()
        self._preroll.clear()  # the needle may have moved while the board was away
        self._phase = "connecting"
        self._emit(host_s)

    def disconnected(self, host_s: float, why: str) -> None:
        self._record(host_s, "disconnect", why)
        self.health.disconnected(host_s, why)
        self._finish(host_s, "disconnected")
        self._phase = "disconnected"
        self._emit(host_s)

    def partial(self, host_s: float, raw: bytes) -> None:
        """The first bytes after a connect, up to the first line break: cut off mid-line, dropped."""
        self._record(host_s, "partial", escape(raw))

    def line(self, host_s: float, raw: bytes) -> None:
        """One complete line (without its line break) that arrived at host time `host_s`."""
        self._record(host_s, "line", escape(raw))
        got = parse_line(raw, len(self.settings.channels), self.settings.adc_max)
        if got is None:
            return
        if isinstance(got, str):
            self.health.garbage(host_s, got)
            self._emit(host_s)
        elif isinstance(got, Banner):
            self._take_banner(got)
        else:
            self._sample(host_s, got)

    def tick(self, host_s: float) -> None:
        """Nothing arrived for a while: let the displays show silence or a fault (a state when the
        problems change, else at most every TICK_S: a frame's own state is what the page waits for)."""
        problems = {**self.health.problems(host_s), **self.notes}
        if problems != self._last_state.get("problems") or host_s - self._last_emit >= TICK_S:
            self._emit(host_s)

    def close(self, host_s: float) -> dict[str, Any]:
        """End the session: the insertion under way is closed; the totals."""
        self._finish(host_s, "session end")
        summary = {
            "insertions": [i.summary() for i in self.insertions],
            "counts": dict(self.health.counts),
            "notes": dict(self.notes),
            "model": self.client.name,
            "calibrated": self.client.calibrated,
        }
        if self.recorder is not None:
            self.recorder.close(summary)
        return summary

    # --- inside -----------------------------------------------------------------------------------

    def _record(self, host_s: float, kind: str, text: str) -> None:
        if self._t0_host is None:
            self._t0_host = host_s
        if self.recorder is not None:
            self.recorder.line(host_s, kind, text)

    def _take_banner(self, banner: Banner) -> None:
        self.banner = banner
        s = self.settings
        if banner.channels is not None and len(banner.channels) != len(s.channels):
            self.notes["banner"] = (
                f"the firmware says {len(banner.channels)} channel(s) {list(banner.channels)}; "
                f"the model reads {len(s.channels)}"
            )
        changes: dict[str, Any] = {}
        if banner.adc_bits is not None and "adc_bits" not in self.fixed:
            changes["adc_bits"] = banner.adc_bits
        if banner.vref_v is not None and "vref_v" not in self.fixed:
            changes["vref_v"] = banner.vref_v
        if changes:
            self.settings = StreamSettings(**{**s.__dict__, **changes})
            if self.recorder is not None:
                self.recorder.update_sensor(**changes)
        unit = self.client.unit_id
        if banner.unit_id and unit and banner.unit_id != unit:
            self.notes["unit"] = (
                f"the firmware says unit {banner.unit_id}, the session applies {unit}'s settings"
            )

    def _board_time(self, host_s: float, millis: int) -> tuple[float, float | None]:
        """(board time in s, the time since the previous sample or None after a connect or restart)."""
        prev = self._prev_millis
        self._prev_millis = millis
        if prev is None:
            # a new stream: continue the session's time by the host's clock, so it never goes back
            gap = (
                0.0 if self._last_host is None else max(host_s - self._last_host, 1.0 / self.settings.rate_hz)
            )
            self._t += gap
            return self._t, None
        delta = (millis - prev) % MILLIS_WRAP  # a wrap of the 32-bit millis is a small step
        if delta == 0 or delta > RESTART_MS:
            self.notes["restart"] = "the board's clock went back: it restarted"
            self.detector.reset()
            self._preroll.clear()
            self._finish(host_s, "restart")
            self._t += 1.0 / self.settings.rate_hz
            return self._t, None
        self._t += delta / 1000.0
        return self._t, delta / 1000.0

    def _plausible_clock(self, millis: int) -> bool:
        """False for a line whose board time jumps back or far ahead, unless the board has just booted
        (small millis) or the next line carries on from it: one garbled digit is garbage, not a restart."""
        prev, suspect = self._prev_millis, self._suspect
        self._suspect = None
        if prev is None or 0 < (millis - prev) % MILLIS_WRAP <= RESTART_MS or millis < RESTART_MS:
            return True
        if suspect is not None and 0 < (millis - suspect) % MILLIS_WRAP <= 1000:
            return True  # two lines agree on the new clock: the board's time really moved
        self._suspect = millis
        return False

    def _sample(self, host_s: float, sample: Sample) -> None:
        if not self._plausible_clock(sample.millis):
            self.health.garbage(host_s, f"board time {sample.millis} ms jumps from {self._prev_millis} ms")
            self._emit(host_s)
            return
        t, gap = self._board_time(host_s, sample.millis)
        self._last_host = host_s
        self.health.sample(host_s, t, gap)
        self.health.channels(host_s, t, sample.counts, self.settings.adc_max, self.settings.channels)
        volts = self.settings.volts(sample.counts)
        host_ms = (host_s - (self._t0_host or host_s)) * 1000.0
        self._phase = "insertion" if self.detector.active else "idle"
        event = self.detector.push(t, volts)
        if event == "start":
            self._begin(host_s)
        elif event in ("end", "timeout"):
            self._finish(host_s, event)
        item = (t, volts, sample.counts, host_ms, sample.millis)
        if self._current is not None:
            self._step(item)
        elif self._current is None:
            self._frame = self.client.step(volts, t)  # the force at rest, for the display
            self._preroll.append(item)
        self._emit(host_s)

    def _begin(self, host_s: float) -> None:
        number = len(self.insertions) + 1
        ins = Insertion(number, f"i{number:03d}", self._t)
        self.insertions.append(ins)
        self._current = ins
        self._phase = "insertion"
        # the registry was polled when the last insertion ended (`_finish`): no network in the frame path
        self.client.reset(poll=False)
        if self.recorder is not None:
            self.recorder.begin_trial(ins.trial_id)
        for item in self._preroll:  # the rest before the start: the tracker's rest reading
            self._step(item)
        self._preroll.clear()

    def _step(self, item: tuple[float, np.ndarray, tuple[int, ...], float, int]) -> None:
        t, volts, counts, host_ms, millis = item
        frame = self.client.step(volts, t)
        self._frame = frame
        ins = self._current
        assert ins is not None
        cue = frame.cue.cue if frame.cue is not None else "none"
        if not ins.cues or ins.cues[-1] != cue:
            ins.cues.append(cue)
        if self.recorder is not None:
            self.recorder.sample(host_ms, millis, counts)
            c = frame.cue
            self.recorder.cue(
                t, cue, None if c is None else c.angle_est_deg, frame.force_n, "" if c is None else c.reason
            )

    def _finish(self, host_s: float, how: str) -> None:
        ins = self._current
        if ins is None:
            return
        ins.end_s, ins.ended = self._t, how
        self._current = None
        self._phase = "idle"
        self.client.reset()  # between insertions: a new champion is swapped in here, never mid-way
        if self.recorder is not None:
            self.recorder.end_trial(
                {
                    "trial_id": ins.trial_id,
                    "angle_deg": f"{self.client.angle_deg:g}",
                    "tissue_point": "live",
                    "start_s": f"{ins.start_s:.3f}",
                    "end_s": f"{ins.end_s:.3f}",
                    "ended": how,
                    "cues": " ".join(ins.cues),
                    "final_cue": ins.cues[-1] if ins.cues else "",
                }
            )

    def state(self, host_s: float) -> dict[str, Any]:
        """What the displays show now."""
        if self.recorder is not None and self.recorder.failed:
            self.notes["recording"] = f"the recording stopped: {self.recorder.failed}"
        frame, c = self._frame, self.client
        cue_state = getattr(frame, "cue", None)
        inside = self._current is not None
        no_cue = None  # why there is no angle cue (needlecue_runtime.cues.pack.NO_CUE_REASONS), if none
        if self._phase in ("connecting", "disconnected"):
            cue, reason = "wait", self._phase
        elif not inside:
            cue, reason = "wait", "at rest: insert when ready"
        elif cue_state is None:
            cue, reason = "none", c.uncalibrated_reason or "this model has no cues"
            no_cue = "uncalibrated" if not c.calibrated else "unavailable"
        else:
            cue, reason, no_cue = cue_state.cue, cue_state.reason, cue_state.no_cue
        contact = c.contact_t if inside else None
        return {
            "seq": self._seq,
            "host_s": host_s,
            "t_s": self._t,
            "phase": self._phase,
            "insertion": self._current.number if inside else None,
            "since_contact_s": None if contact is None else self._t - contact,
            "cue": cue,
            "no_cue": no_cue,
            "reason": reason,
            "angle_est_deg": None if not inside or cue_state is None else cue_state.angle_est_deg,
            "force_n": None if frame is None else [round(float(f), 5) for f in frame.force_n],
            "targets": list(c.targets),  # the axes of force_n, in its order: those the model gives
            "preset_angle_deg": c.angle_deg,
            "model": c.name,
            "unit_id": c.unit_id,
            "calibrated": c.calibrated,
            "uncalibrated_reason": c.uncalibrated_reason,
            "problems": {**self.health.problems(host_s), **self.notes},
            "counts": dict(self.health.counts),
            "history": [i.summary() for i in self.insertions[-HISTORY:]],
        }

    def _emit(self, host_s: float) -> None:
        self._last_emit = host_s
        self._seq += 1
        self._last_state = self.state(host_s)
        self.publish(self._last_state)
