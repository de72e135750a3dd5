"""What the tracker shows: a cue with its reason (`CueState`), and the debounce that holds a new cue
back until it has been the candidate long enough. Standard library only: the client imports it."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class CueState:
    cue: str  # "wait" | "continue" | "correct" | "stop" | "none" (no angle cue)
    angle_est_deg: float | None  # the estimate behind a shown angle cue (None when none is shown)
    reason: str
    no_cue: str | None = None  # with "none": a key of NO_CUE_REASONS


class Debounce:
    """A new candidate cue is shown once it has been the candidate for `hold_s` seconds."""

    __slots__ = ("hold", "pending", "shown", "since")

    def __init__(self, hold_s: float) -> None:
        self.hold = hold_s - 1e-9
        self.reset()

    def reset(self) -> None:
        self.shown, self.pending, self.since = 0, -1, 0.0

    def step(self, t: float, candidate: int) -> int:
        if candidate == self.shown:
            self.pending = -1
        elif candidate != self.pending:
            self.pending, self.since = candidate, t
        if self.pending >= 0 and t - self.since >= self.hold:
            self.shown, self.pending = self.pending, -1
        return self.shown
