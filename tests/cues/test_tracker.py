"""The runtime tracker: causal, right on identifiable angles, debounced, falls back when it must."""

from __future__ import annotations

import itertools
import json

import numpy as np
import pytest

from needlecue_runtime.cues.evidence import Evidence
from needlecue_runtime.cues.pack import EstimatorStage
from needlecue_runtime.cues.tracker import CueTracker
from needlecue_runtime.cues.units import calibration_evidence, unit_readings
from needlecue_runtime.frontend import Circuit, Divider, volts_of
from pipeline.config import CuesParams
from pipeline.cues.packs import build_cue_pack
from tests.cues.synthetic import (
    CHANNELS,
    end_of_insertion,
    make_split,
    make_trial,
    nominal_tracker,
    run_tracker,
)


def test_tracker_from_round_tripped_pack_behaves_the_same(pack30: dict) -> None:
    # given: the pack and its JSON copy
    copy = json.loads(json.dumps(pack30))
    trial = make_trial(15, seed=77, batch_id="x", trial_id="x1")
    # when: both track the same trial
    a = run_tracker(nominal_tracker(pack30, 30), trial)
    b = run_tracker(nominal_tracker(copy, 30), trial)
    # then: the same states
    assert a == b


def test_pack_is_only_for_its_own_preset_angle(pack30: dict) -> None:
    # given: the 30° pack / when: a tracker is asked for 45° / then: a clear error
    with pytest.raises(ValueError, match="preset angle 30"):
        CueTracker(pack30, 45)
    with pytest.raises(ValueError, match="needlecue-cues/5"):
        CueTracker({"format": "other"}, 30)


def test_tracker_is_causal(pack30: dict) -> None:
    # given: a trial, and the same trial whose second half is replaced by something else
    trial = make_trial(45, seed=5, batch_id="x", trial_id="x1")
    half = len(trial) // 2
    other = trial.copy()
    rng = np.random.default_rng(0)
    other.loc[half:, list(CHANNELS)] = rng.uniform(0.2, 1.5, (len(trial) - half, 3))
    other.loc[half:, ["fx", "fy", "fz"]] = rng.uniform(-3, 3, (len(trial) - half, 3))
    tracker = nominal_tracker(pack30, 30)
    # when: tracking both
    full = run_tracker(tracker, trial)
    changed = run_tracker(tracker, other)
    # then: the states before the change are identical (the future never leaks into the past)
    assert full[:half] == changed[:half]


@pytest.mark.parametrize(
    ("true_angle", "expected"), [(30, "continue"), (15, "correct"), (45, "correct"), (0, "stop")]
)
def test_tracker_cues_by_deviation(pack30: dict, true_angle: int, expected: str) -> None:
    # given: a fresh (held-out) trial at the true angle, the preset being 30°
    trial = make_trial(true_angle, seed=900 + true_angle, batch_id="held", trial_id="h1")
    # when: tracking it frame by frame
    states = run_tracker(nominal_tracker(pack30, 30), trial)
    end = int(np.flatnonzero(trial["phase"].to_numpy() == "insertion")[-1])
    # then: the cue at the end of the insertion matches the deviation, with the right angle estimate
    assert states[end].cue == expected
    assert states[end].angle_est_deg == pytest.approx(true_angle)
    assert states[0].cue == "wait"  # no evidence yet on the first frame
    assert states[end].reason


def test_tracker_debounces(pack30: dict) -> None:
    # given: a 30° trial tracked with the default 0.2 s debounce
    trial = make_trial(30, seed=3, batch_id="x", trial_id="x1")
    states = run_tracker(nominal_tracker(pack30, 30), trial)
    cues_seq = [s.cue for s in states]
    t = trial["t_s"].to_numpy()
    # then: every cue shown lasts at least the debounce time (or to the end of the trial)
    changes = [i for i in range(1, len(cues_seq)) if cues_seq[i] != cues_seq[i - 1]] + [len(cues_seq) - 1]
    for a, b in itertools.pairwise(changes):
        assert t[b] - t[a] >= 0.2 - 1e-9 or b == len(cues_seq) - 1


def test_force_above_range_means_stop(pack30: dict) -> None:
    # given: an on-angle trial whose predicted force is far above anything seen in training
    trial = make_trial(30, seed=4, batch_id="x", trial_id="x1")
    force = trial[["fx", "fy", "fz"]].to_numpy() * 10
    # when: tracking it / then: the combined cue stops for the force, the paper method too
    states = run_tracker(nominal_tracker(pack30, 30), trial, force)
    end = int(np.flatnonzero(trial["phase"].to_numpy() == "insertion")[-1])
    assert states[end].cue == "stop"
    assert "force" in states[end].reason


@pytest.mark.parametrize(("true_angle", "expected"), [(30, "continue"), (45, "correct")])
def test_two_angle_tracker_gives_the_right_cue(two_angle_pack: dict, true_angle: int, expected: str) -> None:
    # given: a held-out trial, the preset being 30°
    trial = make_trial(true_angle, seed=700 + true_angle, batch_id="held", trial_id="h1")
    # when: tracking it
    states = run_tracker(nominal_tracker(two_angle_pack, 30), trial)
    # then: the right cue and angle estimate at the end of the insertion
    end = end_of_insertion(trial)
    assert (states[end].cue, states[end].angle_est_deg) == (expected, true_angle)


@pytest.mark.parametrize(
    ("angles", "per_batch", "why"),
    [((30,), 3, "only 30° has training trials"), ((30, 45), 1, "more than 3 in all")],
    ids=["one angle", "too few trials"],
)
def test_without_an_estimator_the_tracker_falls_back_to_the_paper_method(
    params: CuesParams, angles: tuple, per_batch: int, why: str
) -> None:
    # given: training data an angle estimator cannot be fitted on
    train = {float(a): make_split(a, ["b1"], per_batch, seed=3) for a in angles}
    logs: list[str] = []
    # when: building the 30° pack and tracking an on-angle trial with both methods
    pack = build_cue_pack(train, 30, params, log=logs.append)
    trial = make_trial(30, seed=31, batch_id="held", trial_id="h1")
    tracker = nominal_tracker(pack, 30)
    states = run_tracker(tracker, trial)
    paper = run_tracker(nominal_tracker(pack, 30, method="paper"), trial)
    # then: a pack without an estimator that says why (strict JSON, as the registry needs), a warning,
    # and a combined cue that is the paper method's, its reason saying the angle estimate is unavailable
    assert pack["angle_estimator"] is None and why in pack["unavailable"]["angle_estimator"]
    json.dumps(pack, allow_nan=False)
    assert any(m.startswith("warning: no angle estimator") for m in logs)
    assert [s.cue for s in states] == [s.cue for s in paper]
    end = end_of_insertion(trial)
    assert states[end].cue == paper[end].cue != "wait" and states[end].angle_est_deg is None
    assert all(s.reason.startswith("angle estimate unavailable") for s in states[1:])
    assert why in states[end].reason and "paper method: predicted force" in states[end].reason


def test_without_a_contact_there_is_no_profile_and_the_tracker_says_so(params: CuesParams) -> None:
    # given: training trials at the preset angle whose volts never move (no contact detected)
    flat = make_split(30, ["b1"], 3, seed=4)
    flat[list(CHANNELS)] = 0.5
    train = {30.0: flat, 45.0: make_split(45, ["b1"], 3, seed=4)}
    # when: building the 30° pack and tracking a trial
    pack = build_cue_pack(train, 30, params)
    states = run_tracker(
        nominal_tracker(pack, 30, method="paper"), make_trial(30, seed=5, batch_id="x", trial_id="1")
    )
    # then: no profile, no thresholds, each with its reason, and a paper method that waits saying why
    assert pack["standard_profile"] is None and pack["thresholds"]["profile"] == {}
    assert "contact" in pack["unavailable"]["standard_profile"]
    json.dumps(pack, allow_nan=False)
    assert {s.cue for s in states} == {"wait"}
    assert "standard profile unavailable" in states[-1].reason


def _volts(conductance_us: np.ndarray, fe: Circuit) -> np.ndarray:
    """The circuit's output for an FSR of this conductance (the inverse of `conductance_us`)."""
    return volts_of(1e3 / conductance_us, fe)


SUPPLY_SIDE = Divider(circuit="divider", supply_v=5.0, fixed_kohm=10.0, series_kohm=1.62)
GROUND_SIDE = Divider(circuit="divider", supply_v=3.3, fixed_kohm=47.0, fsr_at="ground")


@pytest.mark.parametrize("divider", [SUPPLY_SIDE, GROUND_SIDE], ids=["supply-side", "ground-side"])
@pytest.mark.parametrize("rest_us", [[20.0, 30.0, 25.0], [45.0, 12.0, 60.0]])
def test_the_loading_direction_does_not_depend_on_a_units_preload(rest_us: list[float], divider) -> None:
    # given: an estimator unit's FSRs at rest (its cast-in preload), then the needle's load adding
    # conductance in one direction, as physics says (above actuation G grows with the load), read
    # through the circuit its batches declare
    push = np.array([3.0, 1.0, 2.0])
    p = CuesParams(evidence_levels=(0.05, 0.1, 0.2, 0.4))
    t = np.arange(0.0, 4.0, 1 / 30)
    g = np.array(rest_us) + 20.0 * np.clip(t - 1.0, 0.0, None)[:, None] * push
    ev = Evidence(3, p.evidence_levels, p.contact_threshold, p.contact_samples, p.min_rest_s, divider)
    # when: the frames are fed one by one
    for ti, vi in zip(t.tolist(), _volts(g, divider).tolist(), strict=True):
        ev.push(ti, vi)
    # then: every level is reached and each loading direction is the load's, whatever the preload
    assert ev.stage == len(p.evidence_levels)
    directions = np.reshape(ev.features()[3:], (-1, 3))
    np.testing.assert_allclose(directions, np.tile(push / np.linalg.norm(push), (ev.stage, 1)), atol=1e-6)


def test_a_calibrations_evidence_counts_only_at_the_estimators_own_levels(pack30: dict) -> None:
    # given: the pack's loading levels, and a unit calibration's cue evidence gathered at them or not
    levels = pack30["angle_estimator"]["levels"]
    evidence = {"30": {"n": [1], "means": [[0.1, 0.2, 0.3]]}}
    # then: evidence at the pack's levels is the unit's; at other levels, or none said, it is not
    assert calibration_evidence(pack30, {"levels": levels, "evidence": evidence}) == evidence
    # as a calibration document stores them (6 decimals): small levels (volts, no circuit) still match
    small = {
        **pack30,
        "angle_estimator": {**pack30["angle_estimator"], "levels": [0.022761624777, 0.0455232]},
    }
    assert calibration_evidence(small, {"levels": [0.022762, 0.045523], "evidence": evidence}) == evidence
    assert calibration_evidence(pack30, {"levels": [2 * x for x in levels], "evidence": evidence}) is None
    assert calibration_evidence(pack30, {"evidence": evidence}) is None
    assert calibration_evidence(pack30, None) is None


def _stage(n_features: int) -> EstimatorStage:
    """An evidence stage of six classes a step of 1 apart in every (whitened) feature."""
    return EstimatorStage(
        means=[[float(c)] * n_features for c in range(6)],
        precision=np.eye(n_features).tolist(),
        template_weight=None,
        offset_spread=None,
        temperature=1.0,
        temperatures={},
        outside_limit=None,
        n_train=6,
        cv_accuracy=None,
    )


def _evidence(means_by_stage: list[list[list[float] | None]]) -> dict:
    """Per angle (0 .. 75 by 15), one insertion's mean features at each stage it reached (None: not)."""
    out = {}
    for c in range(6):
        reached = [m[c] for m in means_by_stage if m[c] is not None]
        out[f"{15 * c:g}"] = {"n": [1] * len(reached), "means": reached}
    return out


def _departing_unit(d: float) -> tuple[list, list]:
    """One insertion per angle that fits a shift of the layout of `_stage`, but for its 0° and 75°
    cells, `d` off in every feature from stage 1 on: (stage 0 means, stage 1 means), per angle."""
    fit = [[float(c) + 0.3] * 4 for c in range(6)]
    off = [[v + (d if c in (0, 5) else 0.0) for v in row] for c, row in enumerate(fit)]
    return [r[:2] for r in fit], off


def test_a_departure_is_kept_at_a_later_stage_fewer_angles_reach() -> None:
    # given: a unit departing at stage 1 (its 0° and 75° cells 3 steps off), whose stage 2 only the
    # middle angles reach (where they fit a shift of the training layout)
    rest, off = _departing_unit(3.0)
    middle = [row + [row[0]] * 2 if c in (1, 2, 3, 4) else None for c, row in enumerate(off)]
    evidence = _evidence([rest, off, middle])
    # when
    readings = unit_readings([_stage(2), _stage(4), _stage(6)], [15.0 * c for c in range(6)], evidence)
    # then: the rest reading fits, stage 1 departs, and stage 2 cannot undo it with four cells
    assert [r.departs for r in readings] == [False, True, True]


def test_a_later_stage_every_angle_reaches_judges_the_departure_anew() -> None:
    # given: the same unit, every angle reaching stage 2, whose two new features fit a shift: the
    # departure of stage 1's features is diluted below the neighbours' distance
    rest, off = _departing_unit(3.0)
    deeper = [row + [row[1] - (3.0 if c in (0, 5) else 0.0)] * 2 for c, row in enumerate(off)]
    evidence = _evidence([rest, off, deeper])
    stages, classes = [_stage(2), _stage(4), _stage(6)], [15.0 * c for c in range(6)]
    # when
    readings = unit_readings(stages, classes, evidence)
    # then: stage 2 has more features and as many cells: its own verdict stands
    assert [r.departs for r in readings] == [False, True, False]
    # and a training unit's readings are never tested
    assert not any(r.departs for r in unit_readings(stages, classes, evidence, True))
