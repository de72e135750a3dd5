"""The paper's method fitted: the standard profile and the thresholds on the profile score."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from needlecue_runtime.cues.pack import REFERENCE
from pipeline.config import CuesParams
from pipeline.cues.thresholds import best_thresholds, paper_thresholds, standard_profile
from pipeline.cues.trials import trials_of
from tests.cues.synthetic import CHANNELS, make_split


def test_well_separated_scores_are_cut_between_the_classes() -> None:
    # given: scores of the three true cues in disjoint bands
    rng = np.random.default_rng(0)
    scores = [rng.uniform(0, 1, 200), rng.uniform(2, 3, 200), rng.uniform(4, 5, 200)]
    # when
    t1, t2, bal = best_thresholds(scores)
    # then: each cut falls between two bands, and every frame is told right
    assert 1.0 < t1 <= 2.0 and 3.0 < t2 <= 4.0
    assert bal == pytest.approx(1.0)


def test_a_cue_without_frames_is_left_out_and_none_at_all_gives_no_thresholds() -> None:
    # given: no "stop" frames
    t1, t2, bal = best_thresholds([np.array([0.1, 0.2]), np.array([1.0, 1.1]), np.zeros(0)])
    # then: continue and correct are still told apart
    assert 0.2 < t1 <= 1.0 and bal == pytest.approx(1.0)
    # and: with no frame at all, nothing to cut
    t1, t2, bal = best_thresholds([np.zeros(0)] * 3)
    assert math.isinf(t1) and math.isinf(t2) and math.isnan(bal)


def test_the_standard_profile_is_the_mean_force_since_contact(params: CuesParams) -> None:
    # given: the 30° training trials
    trials = trials_of(make_split(30, ["b1", "b2"], 3, seed=1), CHANNELS, 30.0)
    # when
    profile, contacts = standard_profile(trials, params)
    # then: every trial has a contact, the grid spans the horizon, and the force grows as loading does
    assert len(contacts) == 6 and min(contacts) > 0 and profile["n_trials"] == 6
    grid = round(params.profile_horizon_s / params.profile_dt_s) + 1
    assert len(profile["mean_n"]) == grid and profile["axes"] == ["fx", "fy", "fz"]
    fy = [row[1] for row in profile["mean_n"]]
    assert max(fy) > fy[0] + 0.1 and all(s >= 0 for row in profile["sd_n"] for s in row)


def test_without_a_contact_there_is_no_standard_profile(params: CuesParams) -> None:
    # given: a trial whose volts never leave rest
    frame = make_split(30, ["b1"], 1, seed=1)
    for c in CHANNELS:
        frame[c] = 0.5
    # then
    with pytest.raises(ValueError, match="no training trial of the preset angle has a detectable contact"):
        standard_profile(trials_of(frame, CHANNELS, 30.0), params)


def test_thresholds_are_fitted_per_kind_and_a_model_without_usable_frames_says_why(
    train_by_angle: dict[float, pd.DataFrame], params: CuesParams
) -> None:
    # given: every angle's trials, the 30° profile, a model that predicts the reference force and one
    # whose predictions come with no insertion phase to score
    trials = {a: trials_of(f, CHANNELS, a) for a, f in train_by_angle.items()}
    profile = standard_profile(trials[30.0], params)[0]
    exact = {a: f[["fx", "fy", "fz"]].to_numpy() for a, f in train_by_angle.items()}
    # when
    found, missing = paper_thresholds(trials, 30.0, profile, {"exact": exact}, params, lambda _m: None)
    # then: the reference and the exact model give the same cut points, ordered
    assert set(found) == {REFERENCE, "exact"} and missing == {}
    assert found["exact"] == found[REFERENCE]
    assert 0 < found[REFERENCE]["continue_below"] <= found[REFERENCE]["stop_from"]
    # and: trials without an insertion phase leave no frame to fit on, said per kind
    bare = {a: [tr.__class__(**{**tr.__dict__, "ins_end": -1}) for tr in ts] for a, ts in trials.items()}
    found, missing = paper_thresholds(bare, 30.0, profile, {}, params, lambda _m: None)
    assert found == {} and "no training frame" in missing[f"thresholds.profile.{REFERENCE}"]
