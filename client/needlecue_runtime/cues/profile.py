"""The paper method's profile score: a running, spread-normalised RMS distance between a force and the
preset angle's standard profile since the contact. One code for both sides: the tracker pushes each
live frame into a `ProfileScore`, and the fit (`profile_scores`) replays a whole trial through the same
object to set the thresholds the tracker then cuts the score with. Numpy only: the simulator's client
imports this module.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from needlecue_runtime.cues.pack import StandardProfile


class ProfileScore:
    """The profile score of one insertion, one frame at a time (`push`), from its contact on."""

    __slots__ = ("_dt", "_isd", "_mean", "_n", "axes", "horizon", "n_frames", "z2")

    def __init__(self, profile: StandardProfile, horizon_s: float) -> None:
        self._mean = [tuple(r) for r in profile.mean_n]
        floor2 = float(profile.floor_n) ** 2
        self._isd = [tuple(1.0 / math.sqrt(s * s + floor2) for s in r) for r in profile.sd_n]
        self._dt = float(profile.dt_s)
        self._n = len(self._mean)
        self.horizon = horizon_s + 1e-9
        self.axes = len(self._mean[0]) if self._mean else 0  # the profile's axes, the model's targets
        self.reset()

    def reset(self) -> None:
        self.z2, self.n_frames = 0.0, 0

    def push(self, tau: float, f: Sequence[float]) -> None:
        """Add a frame `tau` seconds after the contact, of force `f` (the profile's axes); frames past
        the profile's horizon do not count."""
        if tau > self.horizon:
            return
        g = int(tau / self._dt + 0.5)
        if g >= self._n:
            g = self._n - 1
        z2 = 0.0
        for fk, mk, sk in zip(f, self._mean[g], self._isd[g], strict=True):
            d = (fk - mk) * sk
            z2 += d * d
        self.z2 += z2
        self.n_frames += 1

    @property
    def score(self) -> float | None:
        """The score so far (None before a frame counted)."""
        return math.sqrt(self.z2 / (self.axes * self.n_frames)) if self.n_frames else None


def profile_scores(
    t: np.ndarray, force: np.ndarray, contact_i: int, profile: StandardProfile, horizon_s: float
) -> np.ndarray:
    """The score the tracker shows at every frame of a trial (NaN before contact): its frames pushed
    into a `ProfileScore` in turn. Past the horizon the score holds, so the loop stops there."""
    out = np.full(len(t), np.nan)
    if contact_i < 0:
        return out
    running = ProfileScore(profile, horizon_s)
    t0 = float(t[contact_i])
    frames = force[contact_i:].tolist()
    for i, (ti, f) in enumerate(zip(t[contact_i:].tolist(), frames, strict=True)):
        if ti - t0 > running.horizon:
            out[contact_i + i :] = running.score
            break
        running.push(ti - t0, f)
        out[contact_i + i] = running.score
    return out
