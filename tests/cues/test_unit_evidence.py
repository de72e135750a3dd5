"""Estimator units in the angle estimator: class means per unit, and a new unit read through its
calibration insertions."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from needlecue_runtime.cues.tracker import CueTracker
from needlecue_runtime.cues.units import unit_evidence
from pipeline.config import CuesParams
from pipeline.cues.packs import build_cue_pack
from pipeline.cues.unit_evidence import evidence_of, trial_features
from tests.cues.synthetic import ANGLES, CHANNELS, make_unit_split, run_tracker, whole_pack


def test_a_calibration_comes_before_the_pack_s_own_record_of_a_unit() -> None:
    # given: a pack that knows the training unit "a"
    pack = whole_pack({"units": {"a": {"0": {"n": [1], "means": [[0.0]]}}}})
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
            run_tracker(tracker, trial.reset_index(drop=True))
            out.append((a, tracker.angle_map_deg))
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
