"""How sure the angle estimator must be: the temperature and the confidence a cue needs."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.config import CuesParams
from pipeline.cues.confidence import CONFIDENCE_GRID, fit_temperature, min_confidence_of, softmax
from pipeline.cues.unit_evidence import TrialFeatures

ANGLES = (0.0, 15.0, 30.0)


def _trial(angle: float, frames: int = 10) -> TrialFeatures:
    return TrialFeatures("u", angle, "b", np.zeros(3), 0, (frames,))


def test_softmax_gives_probabilities_in_the_scores_order() -> None:
    p = softmax(np.array([[0.0, 1.0, 2.0], [5.0, 5.0, 5.0]]))
    assert p.sum(axis=1) == pytest.approx([1.0, 1.0])
    assert list(np.argsort(p[0])) == [0, 1, 2] and p[1] == pytest.approx([1 / 3] * 3)


def test_overconfident_scores_get_a_temperature_above_one() -> None:
    # given: scores that put nearly all weight on one class, right only 60 % of the time
    rng = np.random.default_rng(0)
    y = rng.integers(0, 3, 500)
    guess = np.where(rng.random(500) < 0.6, y, (y + 1) % 3)
    logits = 10.0 * np.eye(3)[guess]
    # when
    temp = fit_temperature(logits, y)
    # then: the posterior is flattened; a flat one says nothing, and keeps 1
    assert temp > 2.0
    assert fit_temperature(np.zeros((5, 3)), np.zeros(5, dtype=int)) == 1.0


def test_auto_confidence_is_the_least_that_keeps_wrong_cues_within_budget() -> None:
    # given: per trial, P(angle): the 0° trials sure and right; the 30° trials 0.8 on 15° (a wrong
    # cue at the 0° and 30° presets) and 0.2 on 30°
    trials = [_trial(0.0), _trial(30.0)]
    probs = [(0, 0, np.array([0.95, 0.05, 0.0])), (1, 0, np.array([0.0, 0.8, 0.2]))]
    params = CuesParams(min_confidence="auto", max_wrong=0.01)
    # when
    c = min_confidence_of(probs, trials, ANGLES, 1, params)
    # then: above 0.8, so the wrong 0.8 is not shown; 0.95 still is
    assert 0.8 < c["min_confidence"] <= 0.95
    assert c["cv_wrong_frames"] == 0.0 and 0.0 < c["cv_coverage"] < 1.0
    assert c["cv_frames"] == 2 * len(ANGLES) * 10


def test_a_pinned_confidence_is_reported_as_pinned() -> None:
    trials = [_trial(0.0), _trial(30.0)]
    probs = [(0, 0, np.array([0.95, 0.05, 0.0])), (1, 0, np.array([0.0, 0.8, 0.2]))]
    c = min_confidence_of(probs, trials, ANGLES, 1, CuesParams(min_confidence=0.7))
    # then: the pinned value, and the wrong cues it lets through: 0.8 on 15° is shown at each preset
    # where 15° and 30° fall in different deviation classes
    assert c["min_confidence"] == 0.7 and c["chosen_by"] == "pinned in params"
    assert c["cv_wrong_frames"] > 0.0


def test_the_auto_grid_is_ordered_within_one_half_and_one() -> None:
    assert list(CONFIDENCE_GRID) == sorted(CONFIDENCE_GRID)
    assert CONFIDENCE_GRID[0] == 0.5 and CONFIDENCE_GRID[-1] == 0.99
