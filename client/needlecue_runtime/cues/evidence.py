"""What the estimator's volts say so far, gathered causally one frame at a time: the rest reading,
the contact, and the loading direction at each level reached (shared by the fit, which replays whole
trials, and the tracker, which runs live). Numpy only: the simulator's client imports this module.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from needlecue_runtime.features import MIN_CONDUCTANCE_US
from needlecue_runtime.frontend import Circuit, conductance_us, conductance_us_of_frame

MIN_VOLTS = 1e-3  # floor before taking logs (an unloaded FSR reads a few mV)


@dataclass(frozen=True)
class UnitMap:
    """A calibrated unit's map on its FSRs' conductance, g' = g A^T + b (µS), as its calibration
    fitted it for the force models (`cue_reading` says when the cues read a unit through it).
    Floored: a map must not open a loaded FSR."""

    matrix: np.ndarray
    offset: np.ndarray

    def apply(self, g: np.ndarray) -> np.ndarray:
        return np.maximum(g @ self.matrix.T + self.offset, MIN_CONDUCTANCE_US)

    @classmethod
    def of(cls, d: Mapping[str, Any]) -> UnitMap:
        """A stored map ({"matrix", "offset"})."""
        return cls(np.asarray(d["matrix"], dtype=np.float64), np.asarray(d["offset"], dtype=np.float64))


class Evidence:
    """What the estimator's volts say so far. `push` one frame at a time; True if the features
    changed (the rest mean moved, or a new loading level was reached)."""

    __slots__ = (
        "_rest_signal",
        "contact_i",
        "contact_t",
        "front_end",
        "levels",
        "min_rest_s",
        "n_ch",
        "n_confirm",
        "pending",
        "rest",
        "rest_n",
        "rest_sum",
        "snaps",
        "t_first",
        "thr",
        "unit_map",
    )

    def __init__(
        self,
        n_ch: int,
        levels: Sequence[float],
        thr: float,
        n_confirm: int,
        min_rest_s: float,
        front_end: Circuit | None,
        unit_map: UnitMap | None = None,
    ):
        self.n_ch, self.levels, self.thr = n_ch, tuple(levels), thr
        self.n_confirm, self.min_rest_s, self.front_end = n_confirm, min_rest_s, front_end
        self.unit_map = unit_map
        self.reset()

    def reset(self) -> None:
        self.rest_sum = [0.0] * self.n_ch
        self.rest_n = 0
        self.t_first: float | None = None
        self.pending: list[tuple[float, list[float], Any]] = []
        self.contact_t: float | None = None
        self.contact_i = -1  # frame index of contact (counted from reset)
        self.rest: list[float] | None = None  # rest mean, frozen at contact
        self._rest_signal: np.ndarray | None = None  # its signal (conductance or volts)
        self.snaps: list[list[float]] = []  # the unit loading direction at each level reached

    @property
    def stage(self) -> int:
        return len(self.snaps)

    def rest_mean(self) -> list[float] | None:
        if self.rest is not None:
            return self.rest
        if self.rest_n == 0:
            return None
        n = self.rest_n
        return [s / n for s in self.rest_sum]

    def rest_ready(self, t: float) -> bool:
        return self.contact_t is not None or (
            self.t_first is not None and t - self.t_first >= self.min_rest_s - 1e-9 and self.rest_n > 0
        )

    def signal(self, volts: Sequence[float]) -> np.ndarray:
        """What the evidence reads of `volts`: the FSRs' conductance through the declared circuit (the
        same for every design of front end), else the volts themselves; through the unit's map on its
        conductance where it is read through one (`cue_reading`)."""
        if self.front_end is None:
            return np.asarray(volts, dtype=np.float64)
        if isinstance(volts, list):  # one frame (every frame after contact): the fast path
            g = np.array(conductance_us_of_frame(volts, self.front_end))
        else:
            g = conductance_us(np.asarray(volts, dtype=np.float64), self.front_end)
        return g if self.unit_map is None else self.unit_map.apply(g)

    def rest_signal(self) -> np.ndarray:
        """The signal of the rest mean (frozen at contact)."""
        if self._rest_signal is None:
            self._rest_signal = self.signal(self.rest)  # type: ignore[arg-type]
        return self._rest_signal

    def loading(self, signal: np.ndarray) -> Any:
        """How far `signal` (one frame, or frames along the first axis) has moved from rest: the norm
        of its log ratio to the rest signal, what the levels are set on. After contact only."""
        return np.sqrt(np.sum(np.log(signal / self.rest_signal()) ** 2, axis=-1))

    def features(self) -> list[float] | None:
        """log of the rest signal per channel, then the unit direction of the signal's change since
        rest at each level reached (the direction, not the size: how hard the tissue pushes back is
        not the angle's business)."""
        rest = self.rest_mean()
        if rest is None:
            return None
        out = np.log(self.signal(rest)).tolist()
        for s in self.snaps:
            out.extend(s)
        return out

    def push(self, t: float, v: list[float], extra: Any = None, i: int = -1) -> tuple[bool, list]:
        """Feed one frame. Returns (features changed, frames that became post-contact now: the
        confirming run, [(t, v, extra)], empty unless contact was just confirmed or already on)."""
        v = [x if x > MIN_VOLTS else MIN_VOLTS for x in v]
        if self.contact_t is not None:
            return self._snap(v), [(t, v, extra)]
        if self.t_first is None:
            self.t_first = t
        if not self.rest_ready(t):
            self._add_rest(v)
            return True, []
        n = self.rest_n
        dev = max(abs(math.log(x * n / s)) for x, s in zip(v, self.rest_sum, strict=True))
        if dev > self.thr:
            self.pending.append((t, v, extra, i))
            if len(self.pending) < self.n_confirm:
                return False, []
            self.rest = [s / n for s in self.rest_sum]
            self.contact_t, self.contact_i = self.pending[0][0], self.pending[0][3]
            changed = False
            run = []
            for tp, vp, ep, _ in self.pending:
                changed |= self._snap(vp)
                run.append((tp, vp, ep))
            self.pending = []
            return changed, run
        for _, vp, _, _ in self.pending:  # the run broke: those were rest after all
            self._add_rest(vp)
        self.pending = []
        self._add_rest(v)
        return True, []

    def _add_rest(self, v: list[float]) -> None:
        rs = self.rest_sum
        for k, x in enumerate(v):
            rs[k] += x
        self.rest_n += 1

    def _snap(self, v: list[float]) -> bool:
        if len(self.snaps) >= len(self.levels):
            return False
        # A level is reached by how far the signal moved from rest (the norm of its log ratio), and
        # the direction is the signal's: above actuation an FSR's conductance grows in proportion to
        # its share of the load, whatever its cast-in preload (docs/units.md, "How the cue estimator
        # reads a unit"). Without a declared circuit there is no conductance: the volts stand in.
        now = self.signal(v)
        norm = float(self.loading(now))
        if norm < self.levels[len(self.snaps)]:
            return False
        dg = now - self.rest_signal()
        size = float(np.sqrt(np.sum(dg * dg))) or 1.0
        direction = (dg / size).tolist()
        while len(self.snaps) < len(self.levels) and norm >= self.levels[len(self.snaps)]:
            self.snaps.append(direction)
        return True
