"""Never confidently wrong: how sure the estimator may be of a unit is cross-validated for the way it
knows the unit (training, calibrated, uncalibrated), and when the evidence does not decide the trainee
sees "no angle cue", with why."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest

from needlecue_runtime.cues.pack import NO_CUE_REASONS
from needlecue_runtime.cues.tracker import CueTracker
from needlecue_runtime.cues.units import departing_levels, reading_of, unit_evidence, validated_reading
from pipeline.config import CuesParams
from pipeline.cues.confidence import CONFIDENCE_GRID, reading_confidence
from pipeline.cues.packs import build_cue_pack
from pipeline.cues.trials import replay_evidence, stage_frames, trials_of
from pipeline.cues.unit_evidence import evidence_of, trial_features
from tests.cues.synthetic import ANGLES, CHANNELS, make_trial, make_unit_split, run_tracker

PARAMS = CuesParams(kinds=("ls",), evidence_levels=(0.05, 0.1, 0.2))


def _units_train(units: str) -> dict[float, pd.DataFrame]:
    return {
        float(a): pd.concat(
            [make_unit_split(a, u, [f"{u}-b1", f"{u}-b2"], 3, seed=k + 1) for k, u in enumerate(units)],
            ignore_index=True,
        )
        for a in ANGLES
    }


@pytest.fixture(scope="module")
def three_unit_pack() -> dict:
    return build_cue_pack(_units_train("ABC"), 30, PARAMS)


@pytest.fixture(scope="module")
def one_unit_pack() -> dict:
    return build_cue_pack(_units_train("A"), 30, PARAMS)


def test_a_unit_is_read_by_how_the_estimator_knows_it(three_unit_pack: dict) -> None:
    # given / when / then: a calibration first, then a training unit, else uncalibrated
    one = {"0": {"n": [1], "means": [[0.0]]}, "15": {"n": [2], "means": [[0.0]]}}
    assert reading_of(three_unit_pack, "D", one) == "calibrated-1"  # the fewest insertions at an angle
    assert reading_of(three_unit_pack, "D", {"0": {"n": [3], "means": [[0.0]]}}) == "calibrated-3"
    assert reading_of(three_unit_pack, "A", None) == "training"
    assert reading_of(three_unit_pack, "X", None) == "uncalibrated"
    assert reading_of(three_unit_pack, None, None) == "uncalibrated"


def test_new_units_get_their_own_cross_validated_temperature_and_confidence(
    three_unit_pack: dict, one_unit_pack: dict
) -> None:
    # given: estimators fitted on three units and on one
    est3, est1 = three_unit_pack["angle_estimator"], one_unit_pack["angle_estimator"]
    # then: with three units, leaving one out says how sure to be of a calibrated or an uncalibrated
    # new unit; with one, nothing can be left out
    # (each unit has 6 trials per angle: calibrated from 1, 2 or 3 of them, scored on the rest; the
    # two units left bound no third unit's offset, so an uncalibrated one is not validated)
    readings = {"calibrated-1", "calibrated-2", "calibrated-3"}
    assert set(est3["confidence"]) == {"training", *readings}
    assert all(set(s["temperatures"]) == readings for s in est3["stages"])
    assert set(est1["confidence"]) == {"training"} and all(s["temperatures"] == {} for s in est1["stages"])
    for c in est3["confidence"].values():
        # the least confidence on the grid that keeps the cross-validated wrong frames under max_wrong
        assert c["min_confidence"] in CONFIDENCE_GRID and c["cv_wrong_frames"] <= PARAMS.max_wrong
    # and a tracker takes the numbers of the way it knows its unit
    tracker = CueTracker(three_unit_pack, 30, unit_evidence=unit_evidence(three_unit_pack, "A"))
    assert tracker.min_confidence == est3["confidence"]["training"]["min_confidence"]
    tracker.set_unit(None, "calibrated-2")
    assert tracker.reading == "calibrated-2"
    assert tracker.min_confidence == est3["confidence"]["calibrated-2"]["min_confidence"]
    # an uncalibrated unit, not validated with three training units: no angle cue at all
    tracker.set_unit(None, "uncalibrated")
    assert not any(r.known for r in tracker._readings)


def test_a_new_unit_whose_cross_validation_breaks_the_budget_at_the_training_value_gets_its_own() -> None:
    # given: two angles 30 degrees apart (continue or stop), one cross-validated trial of each; the unit
    # left out reads the 0-degree trial as 30 degrees with P 0.9, the other right with P 0.95
    trials = [SimpleNamespace(angle=0.0, frames=[10]), SimpleNamespace(angle=30.0, frames=[10])]
    wrong, right = (0, 0, np.array([0.1, 0.9])), (1, 0, np.array([0.05, 0.95]))
    # when: the training units' value is 0.8, which shows that wrong cue
    broken = reading_confidence([wrong, right], trials, [0.0, 30.0], 1, PARAMS, 0.8)
    # then: the unit gets the least value that hides it, and says why
    assert broken["min_confidence"] == 0.91 > 0.8 and broken["cv_wrong_frames"] == 0.0
    assert broken["chosen_by"].startswith("its own")
    # and where the training units' value holds the unit's budget, the unit keeps it
    kept = reading_confidence([right], trials, [0.0, 30.0], 1, PARAMS, 0.8)
    assert kept["min_confidence"] == 0.8 and kept["chosen_by"].startswith("the training units'")
    # and a pinned confidence stays pinned, its wrong cues reported
    pinned = PARAMS.model_copy(update={"min_confidence": 0.8})
    assert reading_confidence([wrong, right], trials, [0.0, 30.0], 1, pinned, 0.8)["cv_wrong_frames"] == 0.5


def test_a_pinned_confidence_is_kept_and_scored() -> None:
    # given: min_confidence pinned in params
    params = PARAMS.model_copy(update={"min_confidence": 0.93})
    pack = build_cue_pack(_units_train("AB"), 30, params)
    # then: every reading uses it, and the pack says what it gave in cross-validation
    confidence = pack["angle_estimator"]["confidence"]
    assert confidence["training"]["chosen_by"] == "pinned in params"
    for c in confidence.values():
        assert c["min_confidence"] == 0.93
        assert 0.0 <= c["cv_wrong_frames"] <= 1.0 and 0.0 <= c["cv_coverage"] <= 1.0


def test_with_one_training_unit_an_uncalibrated_unit_gets_no_angle_cue_and_says_why(
    one_unit_pack: dict,
) -> None:
    # given: the pack of one training unit, and a trial of another unit it has no evidence of
    trial = make_unit_split(45, "D", ["D-heldout"], 1, seed=60)
    # when: tracked as an uncalibrated unit
    states = run_tracker(CueTracker(one_unit_pack, 30, reading="uncalibrated"), trial)
    # then: never an angle cue, and the reason is the trainee's "uncalibrated unit"
    after_rest = [s for s in states if s.cue != "wait"]
    assert after_rest and {s.cue for s in after_rest} == {"none"}
    assert {s.no_cue for s in after_rest} == {"uncalibrated"}
    assert NO_CUE_REASONS["uncalibrated"] in after_rest[-1].reason


def test_the_same_unit_calibrated_gets_cues_from_one_insertion_per_angle(one_unit_pack: dict) -> None:
    # given: one training unit, and unit D's one calibration insertion per angle (the case that
    # failed: its calibration evidence used to change nothing)
    levels = one_unit_pack["angle_estimator"]["levels"]
    calib = {float(a): make_unit_split(a, "D", ["D-cal"], 1, seed=50) for a in ANGLES}
    evidence = evidence_of(trial_features(calib, CHANNELS, PARAMS, levels=levels)[0], len(CHANNELS))["D"]
    held = {float(a): make_unit_split(a, "D", ["D-heldout"], 3, seed=60) for a in ANGLES}
    assert departing_levels(one_unit_pack, evidence) == []  # D is laid out as the training unit A
    # when: D's held-out insertions are tracked with its calibration
    right = []
    for a, frame in held.items():
        for _, trial in frame.groupby("trial_id", sort=True):
            tracker = CueTracker(one_unit_pack, 30, unit_evidence=evidence, reading="calibrated-1")
            assert tracker.reading == "training"  # one training unit: nothing could be left out
            states = run_tracker(tracker, trial.reset_index(drop=True))
            right.append(tracker.angle_map_deg == a)
            shown = [s for s in states if s.cue in ("continue", "correct", "stop")]
            # then: whatever it shows is never wrong at the end of the insertion
            if shown:
                assert states[-1].cue in (
                    "none",
                    {0: "stop", 15: "correct", 30: "continue", 45: "correct"}[a],
                )
    # and it names the angle of most insertions
    assert np.mean(right) >= 0.75


def test_a_calibration_deeper_than_validated_takes_the_deepest_validated() -> None:
    validated = ["training", "calibrated-1", "calibrated-2", "uncalibrated"]
    assert validated_reading("calibrated-5", validated) == "calibrated-2"
    assert validated_reading("calibrated-1", validated) == "calibrated-1"
    assert validated_reading("calibrated-1", ["training"]) == "training"
    assert validated_reading("uncalibrated", ["training"]) is None  # not validated: no angle cue


def test_an_unknown_reading_is_refused(three_unit_pack: dict) -> None:
    with pytest.raises(ValueError, match="training"):
        CueTracker(three_unit_pack, 30, reading="guessed")


def test_stage_frames_count_the_insertion_frames_each_stage_is_the_latest() -> None:
    # given: one synthetic insertion and three loading levels
    trial = trials_of(make_trial(30, seed=3, batch_id="b", trial_id="t"), CHANNELS, 30.0)[0]
    ev, starts = replay_evidence(trial, PARAMS, (0.05, 0.1, 0.2))
    # when
    frames = stage_frames(trial, starts)
    # then: one count per stage reached, in order of the stages' starts, adding up to the insertion
    # frames from the first stage on
    assert len(frames) == ev.stage + 1 == len(starts)
    assert starts == sorted(starts)
    assert sum(frames) == trial.ins_end + 1 - max(trial.ins_start, starts[0])


def _turned(frame: pd.DataFrame, unit_id: str) -> pd.DataFrame:
    """The insertions as a unit whose connector is turned by a third reads them: channels rotated."""
    out = frame.assign(unit_id=unit_id)
    out[list(CHANNELS)] = frame[[CHANNELS[1], CHANNELS[2], CHANNELS[0]]].to_numpy()
    return out


def test_a_new_unit_laid_out_unlike_the_training_unit_says_outside_instead_of_guessing(
    one_unit_pack: dict,
) -> None:
    # given: one training unit, and a new unit T whose channels are rotated (a turned connector: no
    # shift of the training unit's classes matches it), calibrated from one insertion per angle
    levels = one_unit_pack["angle_estimator"]["levels"]
    calib = {float(a): _turned(make_unit_split(a, "A", ["T-cal"], 1, seed=50), "T") for a in ANGLES}
    evidence = evidence_of(trial_features(calib, CHANNELS, PARAMS, levels=levels)[0], len(CHANNELS))["T"]
    held = {float(a): _turned(make_unit_split(a, "A", ["T-heldout"], 2, seed=60), "T") for a in ANGLES}
    # (the cues stage names the stages where it departs: here every one, the rest reading too)
    assert departing_levels(one_unit_pack, evidence) == list(range(len(levels) + 1))
    for frame in held.values():
        for _, trial in frame.groupby("trial_id", sort=True):
            # when: tracked with its calibration
            tracker = CueTracker(one_unit_pack, 30, unit_evidence=evidence, reading="calibrated-1")
            states = run_tracker(tracker, trial.reset_index(drop=True))
            # then: no angle cue at all, and the trainee is told the evidence is outside training
            assert {s.cue for s in states} <= {"wait", "none"}
            assert states[-1].no_cue == "outside"
            assert NO_CUE_REASONS["outside"] in states[-1].reason
