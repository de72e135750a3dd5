"""Estimator units in the angle estimator: class means per unit, and a new unit read through its
calibration insertions."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from pipeline.config import CuesParams
from pipeline.cues.fit import build_cue_pack
from pipeline.cues.tracker import CueTracker, class_means, unit_evidence
from pipeline.cues.units import evidence_of, trial_features
from tests.cues.synthetic import ANGLES, CHANNELS, make_unit_split, run_tracker

MU = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])


def test_a_unit_without_evidence_is_read_as_the_average_unit() -> None:
    # given / when: no cells / then: the average unit's means
    np.testing.assert_array_equal(class_means(MU, [], 2.0, 1.0), MU)


def test_a_well_measured_offset_shifts_every_class() -> None:
    # given: many trials at two of three angles, all sitting 0.5 off the average unit
    d = np.array([0.5, -0.5])
    cells = [(0, 1e6, MU[0] + d), (2, 1e6, MU[2] + d)]
    # when: no pull (k None), a wide offset spread
    out = class_means(MU, cells, None, 1e6)
    # then: every class moves by the offset, the angle without trials too
    np.testing.assert_allclose(out, MU + d, atol=1e-6)


def test_offset_is_shrunk_by_how_well_few_trials_pin_it_down() -> None:
    # given: one trial at one angle (its variance 1/n = 1) and an offset spread of 1
    cells = [(1, 1.0, MU[1] + np.array([1.0, 0.0]))]
    # when / then: half the offset (spread / (spread + variance))
    np.testing.assert_allclose(class_means(MU, cells, None, 1.0)[0], [0.5, 0.0])
    # and with no spread known, no shift at all
    np.testing.assert_array_equal(class_means(MU, cells, None, None), MU)


def test_a_unit_s_trials_pull_their_class_by_count_against_the_weight() -> None:
    # given: one trial at angle 0, k = 2, no shift
    cells = [(0, 1.0, np.array([3.0, 3.0]))]
    # when
    out = class_means(MU, cells, 2.0, None)
    # then: (1 * trial + 2 * mean) / 3 at that angle, the others unchanged
    np.testing.assert_allclose(out[0], [1.0, 1.0])
    np.testing.assert_array_equal(out[1:], MU[1:])


def test_a_calibration_comes_before_the_pack_s_own_record_of_a_unit() -> None:
    # given: a pack that knows the training unit "a"
    pack = {"angle_estimator": {"units": {"a": {"0": {"n": [1], "means": [[0.0]]}}}}}
    mine = {"0": {"n": [1], "means": [[1.0]]}}
    # when / then
    assert unit_evidence(pack, "a") == pack["angle_estimator"]["units"]["a"]
    assert unit_evidence(pack, "a", mine) == mine
    assert unit_evidence(pack, "b") is None
    assert unit_evidence(pack, None) is None


@pytest.fixture(scope="module")
def unit_setup() -> dict:
    params = CuesParams(kinds=("ls",), evidence_levels=(0.05, 0.1, 0.2))
    train = {
        float(a): pd.concat(
            [make_unit_split(a, u, [f"{u}-b1", f"{u}-b2"], 3, seed=k + 1) for k, u in enumerate("ABC")],
            ignore_index=True,
        )
        for a in ANGLES
    }
    calib = {float(a): make_unit_split(a, "D", ["D-cal"], 1, seed=50) for a in ANGLES}
    heldout = {float(a): make_unit_split(a, "D", ["D-heldout"], 6, seed=60) for a in ANGLES}
    return {"params": params, "train": train, "calib": calib, "heldout": heldout}


def _final_estimates(pack: dict, heldout: dict, evidence: dict | None) -> list[tuple[float, float]]:
    tracker = CueTracker(pack, 30, unit_evidence=evidence)
    out = []
    for a, frame in heldout.items():
        for _, trial in frame.groupby("trial_id", sort=True):
            states = run_tracker(tracker, trial.reset_index(drop=True))
            out.append((a, states[-1].angle_est_deg))
    return out


def test_a_new_unit_is_read_right_after_one_calibration_insertion_per_angle(unit_setup: dict) -> None:
    # given: an estimator fitted on units A, B, C, and unit D's one calibration insertion per angle
    p = unit_setup["params"]
    pack = build_cue_pack(unit_setup["train"], 30, p)
    levels = pack["angle_estimator"]["levels"]  # D's evidence is gathered where the estimator's was
    trials = trial_features(unit_setup["calib"], CHANNELS, p, levels=levels)[0]
    evidence = evidence_of(trials, len(CHANNELS))["D"]
    # when: D's held-out insertions are read with and without its calibration
    calibrated = _final_estimates(pack, unit_setup["heldout"], evidence)
    uncalibrated = _final_estimates(pack, unit_setup["heldout"], None)
    # then: the calibrated reading names the angle of nearly every insertion, and beats the other
    right_cal = np.mean([a == est for a, est in calibrated])
    right_uncal = np.mean([a == est for a, est in uncalibrated])
    assert right_cal >= 0.9
    assert right_cal > right_uncal
    # and the pack remembers the training units, not the new one
    assert sorted(pack["angle_estimator"]["units"]) == ["A", "B", "C"]
