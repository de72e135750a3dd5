"""The loading levels the angle estimator samples the direction at: set by the training trials, so
that a rig whose signal moves less under the same push still passes every level."""

from __future__ import annotations

import numpy as np
import pandas as pd

from pipeline.config import AUTO_EVIDENCE_LEVELS, CuesParams
from pipeline.cues.trials import AUTO_REACH, loading_levels, run_evidence, trials_of
from tests.cues.synthetic import ANGLES, CHANNELS, make_split

AUTO = CuesParams(kinds=("ls",))


def _trials(frames: dict[float, pd.DataFrame]):
    return [tr for a, f in frames.items() for tr in trials_of(f, CHANNELS, a)]


def test_auto_levels_follow_how_far_the_rigs_signal_moves() -> None:
    # given: training trials, and the same trials on a rig whose signal moves half as far in log
    # (every reading the square root of the first rig's)
    frames = {float(a): make_split(a, ["b1", "b2"], 3, seed=7) for a in ANGLES}
    softer = {a: f.assign(**{c: np.sqrt(f[c]) for c in CHANNELS}) for a, f in frames.items()}
    # when: the levels are left to the data
    levels = loading_levels(_trials(frames), AUTO)
    half = loading_levels(_trials(softer), AUTO)
    # then: there are as many as promised, evenly spaced, and the softer rig's are half as high
    assert len(levels) == AUTO_EVIDENCE_LEVELS
    np.testing.assert_allclose(np.diff(levels), levels[0], rtol=2e-3)
    np.testing.assert_allclose(half, np.array(levels) / 2, rtol=2e-2)  # rest: a mean of readings
    # and on each rig at least AUTO_REACH of the trials pass every level
    for trials, lv in ((_trials(frames), levels), (_trials(softer), half)):
        reached = [run_evidence(tr, AUTO, lv).stage == len(lv) for tr in trials]
        assert np.mean(reached) >= AUTO_REACH


def test_pinned_levels_are_used_as_they_are() -> None:
    frames = {0.0: make_split(0, ["b1"], 2, seed=3)}
    pinned = CuesParams(kinds=("ls",), evidence_levels=(0.05, 0.1))
    assert loading_levels(_trials(frames), pinned) == (0.05, 0.1)
