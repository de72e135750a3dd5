"""Where an insertion starts and ends, read from the estimator's volts alone.

At rest the three FSRs read a steady preload. An insertion starts when some channel moves more than
`start_rel` (relative) from the rest reading for `start_frames` frames in a row; it ends when every
channel is back within `end_rel` of the rest reading for `end_hold_s`; or the signal has been steady
(every channel within `steady_rel`) for `steady_end_s` near the rest reading (within
`steady_end_rel`: the needle put down at another angle, silicone that has not crept back yet); or
after `max_s`. In the simulated held-out and calibration trials (102 trials), a steady stretch in the
first 9 s of an insertion is at least 32 % from the rest reading, so `steady_end_rel` 20 % never
ends an insertion mid-way there. While idle,
the rest reading follows slow drift: it is the median of the last `rest_s` whenever that second is
steady. The thresholds sit above a 10-bit ADC's one-count step at the FSRs' rest readings (about 1 %)
and below the first second of loading in the simulated and recorded trials (tens of %).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class InsertionRules:
    start_rel: float = 0.10
    start_frames: int = 3
    end_rel: float = 0.06
    end_hold_s: float = 1.0
    max_s: float = 60.0
    rest_s: float = 1.0
    steady_rel: float = 0.03  # a second whose channels span less than this (relative) is steady
    steady_end_s: float = 1.5
    steady_end_rel: float = 0.20
    floor_v: float = 0.05  # relative changes are taken against at least this many volts


class InsertionDetector:
    """`push(t, volts)` -> "start", "end", "timeout" or None. `active` is True inside an insertion."""

    def __init__(self, rate_hz: float, rules: InsertionRules | None = None) -> None:
        self.rules = rules or InsertionRules()
        self._n_rest = max(3, round(self.rules.rest_s * rate_hz))
        self._recent: deque[tuple[float, np.ndarray]] = deque(maxlen=self._n_rest)
        self._n_steady = max(3, round(self.rules.steady_end_s * rate_hz))
        self._window: deque[np.ndarray] = deque(maxlen=self._n_steady)
        self.reset()

    def reset(self) -> None:
        """Forget the rest reading and any insertion (after a reconnect: the needle may have moved)."""
        self._recent.clear()
        self._window.clear()
        self.rest: np.ndarray | None = None
        self.active = False
        self.started_at: float | None = None
        self._above = 0
        self._calm_since: float | None = None

    def _relative(self, v: np.ndarray) -> float:
        assert self.rest is not None
        return float(np.max(np.abs(v - self.rest) / np.maximum(self.rest, self.rules.floor_v)))

    def push(self, t: float, volts: np.ndarray) -> str | None:
        r = self.rules
        v = np.asarray(volts, dtype=np.float64)
        self._recent.append((t, v))
        if not self.active:
            if len(self._recent) == self._n_rest and self._span(x for _, x in self._recent) < r.steady_rel:
                self.rest = np.median(np.array([x for _, x in self._recent]), axis=0)
            if self.rest is None:
                return None
            self._above = self._above + 1 if self._relative(v) > r.start_rel else 0
            if self._above >= r.start_frames:
                self.active, self.started_at, self._calm_since = True, t, None
                return "start"
            return None
        assert self.started_at is not None
        if t - self.started_at > r.max_s:
            self._stop()
            return "timeout"
        self._window.append(v)
        rel = self._relative(v)
        if (
            rel <= r.steady_end_rel
            and len(self._window) == self._n_steady
            and self._span(self._window) < r.steady_rel
        ):
            self._stop()
            return "end"
        if rel <= r.end_rel:
            if self._calm_since is None:
                self._calm_since = t
            if t - self._calm_since >= r.end_hold_s:
                self._stop()
                return "end"
        else:
            self._calm_since = None
        return None

    def _span(self, rows: Iterable[np.ndarray]) -> float:
        """The largest relative spread of a channel over `rows`."""
        block = np.array(list(rows))
        return float(
            (
                (block.max(axis=0) - block.min(axis=0)) / np.maximum(block.min(axis=0), self.rules.floor_v)
            ).max()
        )

    def _stop(self) -> None:
        # the rest is read again: the needle may rest elsewhere now (another angle, creeping silicone)
        self.active, self.started_at, self._above, self._calm_since, self.rest = False, None, 0, None, None
        self._recent.clear()
        self._window.clear()
