"""The paper method's profile score: one code for the live tracker and for the fit of its thresholds."""

from __future__ import annotations

import math

import numpy as np
import pytest

from needlecue_runtime.cues.pack import StandardProfile, as_pack
from needlecue_runtime.cues.profile import ProfileScore, profile_scores
from needlecue_runtime.cues.tracker import CueTracker
from pipeline.config import CuesParams
from pipeline.cues.trials import run_evidence, trials_of
from tests.cues.synthetic import CHANNELS, make_trial


def _profile(
    mean: list[list[float]], sd: list[list[float]], floor: float = 0.0, dt: float = 0.5
) -> StandardProfile:
    return StandardProfile(
        dt_s=dt, axes=["fx", "fy"], mean_n=mean, sd_n=sd, floor_n=floor, n_trials=1, time_origin="contact"
    )


def test_a_force_on_the_profile_scores_zero_and_one_spread_off_scores_one() -> None:
    # given: a two-axis profile with a spread of 0.5 N and no floor
    profile = _profile([[1.0, 2.0], [1.5, 2.5]], [[0.5, 0.5], [0.5, 0.5]])
    on, off = ProfileScore(profile, 10.0), ProfileScore(profile, 10.0)
    # when: one insertion follows the mean, the other sits one spread above it on both axes
    for tau, mean in [(0.0, [1.0, 2.0]), (0.5, [1.5, 2.5]), (1.0, [1.5, 2.5])]:
        on.push(tau, mean)
        off.push(tau, [m + 0.5 for m in mean])
    # then: 0 and 1, an RMS over frames and axes
    assert on.score == 0.0
    assert off.score == pytest.approx(1.0)


def test_no_score_before_a_frame_and_frames_past_the_horizon_do_not_count() -> None:
    # given: a profile and a horizon of 1 s
    score = ProfileScore(_profile([[0.0, 0.0]], [[1.0, 1.0]]), 1.0)
    # then: nothing before the first frame
    assert score.score is None
    # when: a frame at the contact, 2 N off on one axis, and one past the horizon far off
    score.push(0.0, [2.0, 0.0])
    score.push(1.5, [100.0, 100.0])
    # then: only the first counts: sqrt(4 / 2 axes)
    assert score.n_frames == 1 and score.score == pytest.approx(math.sqrt(2.0))


def test_the_floor_bounds_how_far_a_narrow_profile_calls_a_force() -> None:
    # given: a profile with no spread, and a floor of 0.1 N
    profile = _profile([[0.0, 0.0]], [[0.0, 0.0]], floor=0.1)
    score = ProfileScore(profile, 1.0)
    # when: a force 0.1 N off on both axes
    score.push(0.0, [0.1, 0.1])
    # then: one floor off, not infinitely far
    assert score.score == pytest.approx(1.0)


def test_the_batch_scores_hold_after_the_horizon_and_are_nan_before_contact() -> None:
    # given: a trial of 6 frames at 1 s, its contact at frame 2, a horizon of 2 s
    profile = _profile([[0.0, 0.0]], [[1.0, 1.0]])
    t = np.arange(6.0)
    force = np.array([[9.0, 9.0], [9.0, 9.0], [1.0, 1.0], [3.0, 3.0], [0.0, 0.0], [50.0, 50.0]])
    # when
    s = profile_scores(t, force, 2, profile, 2.0)
    # then: NaN before contact, the running RMS up to the horizon, then it holds
    assert np.isnan(s[:2]).all()
    assert s[2] == pytest.approx(1.0) and s[3] == pytest.approx(math.sqrt(5.0))
    assert s[4] == pytest.approx(math.sqrt(10 / 3)) and s[5] == s[4]
    # and: without a contact, no score at all
    assert np.isnan(profile_scores(t, force, -1, profile, 2.0)).all()


@pytest.mark.parametrize("angle", [30.0, 45.0])
def test_the_tracker_and_the_fit_compute_the_same_profile_score(
    pack30: dict, params: CuesParams, angle: float
) -> None:
    # given: the 30° pack, and a trial at `angle` with a force that departs from the profile
    frame = make_trial(angle, seed=7, batch_id="x", trial_id="t1")
    force = frame[["fx", "fy", "fz"]].to_numpy() * 1.3 + 0.05
    tracker = CueTracker(pack30, 30.0, method="paper")
    # when: the tracker is fed it frame by frame, as live
    live = []
    volts = frame[list(CHANNELS)].to_numpy()
    for i, t in enumerate(frame["t_s"].to_numpy()):
        tracker.update(t, volts[i], force[i])
        live.append(math.nan if tracker.profile_score is None else tracker.profile_score)
    # and: the fit scores the whole trial at once, from the contact the same evidence finds
    trial = trials_of(frame, CHANNELS, angle)[0]
    contact = run_evidence(trial, params).contact_i
    pack = as_pack(pack30)
    batch = profile_scores(
        trial.t, force[trial.rows], contact, pack.standard_profile, params.profile_horizon_s
    )
    # then: the very same numbers, frame by frame, from the frame the tracker confirms the contact
    # (a divergence would set thresholds the tracker then cuts another score with); before it, the
    # tracker is still confirming the contact and shows none
    shown = np.asarray(live)[trial.rows]
    confirmed = contact + params.contact_samples - 1
    assert contact > 0 and np.isfinite(batch).sum() > 10
    assert np.isnan(shown[:confirmed]).all()
    assert np.array_equal(shown[confirmed:], batch[confirmed:])
