"""Scoring the cues: hand-checked confusion matrices and times to cue."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from needlecue_runtime.vocab import angle_name
from pipeline.config import CuesParams
from pipeline.cues.document import write_cue_evaluation
from pipeline.cues.packs import build_cue_pack
from pipeline.cues.score import evaluate_cues, track_external
from pipeline.cues.summary import Run, summarise_runs, time_to_cue
from pipeline.cues.unit_groups import evaluate_unit_groups
from pipeline.reporting import cue_figures
from pipeline.reporting import cues as cue_report
from tests.cues.synthetic import (
    ANGLES,
    external_split,
    make_split,
    make_unit_split,
    zero_forces,
)


def test_summarise_runs_hand_checked() -> None:
    # given: three runs on a 0.5 s grid, insertion from frame 2 to frame 7
    t = np.arange(10) * 0.5
    W, C, K, S, N = 0, 1, 2, 3, 4  # wait, continue, correct, stop, none (no angle cue)
    runs = [
        # preset 30, true 30 -> continue; wrong (correct) at frame 4, right from frame 5 on: 5 -> 1.5 s
        Run("ls", "combined", 30, 30, t, np.array([W, W, C, C, K, C, C, C, C, C]), 2, 7),
        # preset 30, true 45 -> correct; right from the start (before the insertion): 0 s
        Run("ls", "combined", 30, 45, t, np.array([W, K, K, K, K, K, K, K, S, S]), 2, 7),
        # preset 30, true 60 -> stop; ends on correct: never right
        Run("ls", "combined", 30, 60, t, np.array([W, W, W, S, S, S, K, K, K, K]), 2, 7),
        # preset 0, true 30 -> stop; no angle cue from frame 4, right from frame 7 (the last one): 2.5 s
        Run("ls", "combined", 0, 30, t, np.array([W, W, W, W, N, N, N, S, C, C]), 2, 7),
    ]
    # when
    res = summarise_runs(runs)["ls"]["combined"]
    # then: the final-cue confusion (rows continue/correct/stop; columns wait/continue/correct/stop/none)
    assert res["confusion_final"]["counts"] == [[0, 1, 0, 0, 0], [0, 0, 1, 0, 0], [0, 0, 1, 1, 0]]
    assert res["accuracy_final"] == pytest.approx(3 / 4)
    # per frame over frames 2..7: run 1: C,C,K,C,C,C; run 2: K x6; run 3: W,S,S,S,K,K; run 4: W,W,N,N,N,S
    assert res["confusion_frames"]["counts"] == [[0, 5, 1, 0, 0], [0, 0, 6, 0, 0], [3, 0, 2, 4, 3]]
    # what the trainee saw: run 3 ends wrong; runs 1 and 3 showed a wrong cue at some frame; 3 of the
    # 24 insertion frames show a wrong cue, 18 show a cue at all
    assert res["seen"] == {
        "wrong_final": 1 / 4,
        "wrong_ever": 2 / 4,
        "wrong_frames": 3 / 24,
        "coverage_frames": 18 / 24,
    }
    ttc = res["time_to_cue"]
    assert ttc["0"] == {
        "trials": 1,
        "right_at_end": 1,
        "never_right": 0,
        "median_s": 1.5,
        "p90_s": 1.5,
        "seconds": [1.5],
    }
    assert ttc["15"]["median_s"] == 0.0
    assert ttc["30"]["trials"] == 2 and ttc["30"]["never_right"] == 1 and ttc["30"]["seconds"] == [2.5]
    assert ttc[">=45"]["trials"] == 0 and ttc[">=45"]["median_s"] is None


def test_time_to_cue_edge_cases() -> None:
    t = np.arange(5) * 1.0
    assert time_to_cue(t, np.array([1, 1, 1, 1, 1], bool), 1, 3) == 0.0
    assert time_to_cue(t, np.array([1, 0, 1, 1, 0], bool), 1, 3) == 1.0
    assert time_to_cue(t, np.array([1, 1, 1, 0, 1], bool), 1, 3) is None


def test_evaluate_cues_tiny_case(
    tmp_path: Path, train_by_angle: dict, params: CuesParams, pack30: dict
) -> None:
    # given: 2 held-out trials per angle (0, 15, 30, 45), the 30° preset, and angles that the rest
    # reading alone identifies, so the cue is right before the insertion even starts
    external = external_split(2)
    # when: scored with a model that predicts no force at all
    ev = evaluate_cues(external, params, {30: pack30}, zero_forces(external), log=lambda _m: None)
    # then: hand-checked: 0° -> stop (2), 15° and 45° -> correct (4), 30° -> continue (2), all right
    ours = ev["results"]["ls"]["combined"]
    assert ours["confusion_final"]["counts"] == [[0, 2, 0, 0, 0], [0, 0, 4, 0, 0], [0, 0, 0, 2, 0]]
    assert ours["accuracy_final"] == 1.0
    for group, n in (("0", 2), ("15", 4), ("30", 2)):
        assert ours["time_to_cue"][group] == {
            "trials": n,
            "right_at_end": n,
            "never_right": 0,
            "median_s": 0.0,
            "p90_s": 0.0,
            "seconds": [0.0] * n,
        }
    frames = {a: int((make_split(a, ["heldout"], 2, seed=9)["phase"] == "insertion").sum()) for a in ANGLES}
    assert ours["confusion_frames"]["counts"] == [
        [0, frames[30], 0, 0, 0],
        [0, 0, frames[15] + frames[45], 0, 0],
        [0, 0, 0, frames[0], 0],
    ]
    assert ours["seen"] == {
        "wrong_final": 0.0,
        "wrong_ever": 0.0,
        "wrong_frames": 0.0,
        "coverage_frames": 1.0,
    }
    assert ev["angle_estimate_at_insertion_end"]["exact"] == 1.0
    # the paper's method and its measured-force bound are scored on the same trials
    assert np.sum(ev["results"]["ls"]["paper"]["confusion_final"]["counts"]) == 8
    assert np.sum(ev["results"]["reference"]["paper"]["confusion_final"]["counts"]) == 8


def test_evaluation_without_an_estimator_scores_the_paper_method_only(
    tmp_path: Path, train_by_angle: dict, params: CuesParams
) -> None:
    # given: a pack whose estimator could not be fitted, and external trials
    external = external_split(1)
    pack = build_cue_pack(train_by_angle, 30, params, estimator_unavailable="a reason")
    # when: scoring it
    ev = evaluate_cues(external, params, {30: pack}, zero_forces(external), log=lambda _m: None)
    # then: the paper method only, no angle estimate, the reason kept, and a report that says so
    assert set(ev["results"]["ls"]) == {"paper"}
    assert ev["angle_estimate_at_insertion_end"] is None
    assert ev["unavailable"] == {"30": {"angle_estimator": "a reason"}}
    written = write_cue_evaluation(tmp_path / "evaluation.json", ev)  # as the stage writes it
    summary = cue_report.angle_cues(written, {30.0: pack})
    assert "**No angle estimator** (a reason)" in summary and "| LS | profile comparison (paper) |" in summary
    cue_figures.plot_confusion(written, tmp_path / "c.png")
    cue_figures.plot_time_to_cue(written, tmp_path / "t.png")


def test_unit_groups_from_the_evaluations_runs_equal_the_groups_scored_again(
    params: CuesParams, pack30: dict
) -> None:
    # given: external trials at every angle by a training unit and by a calibrated new unit
    external = {
        float(a): pd.concat(
            [
                make_unit_split(a, "est-1", ["heldout"], 2, seed=9),
                make_unit_split(a, "est-9", ["heldout-new"], 2, seed=11),
            ],
            ignore_index=True,
        )
        for a in ANGLES
    }
    roles, calibrated = {"est-1": "training", "est-9": "new"}, {"est-9": True}
    forces = lambda _k, _p, a, _split="external": np.zeros((len(external[a]), 3))  # noqa: E731
    packs = {30: pack30}
    # when: the groups are scored again from their frames, and summarised from the whole evaluation's runs
    tracked = track_external(external, params, packs, forces, log=lambda _m: None)
    groups = (external, {}, params, packs, forces, "external", roles, calibrated)
    replayed = evaluate_unit_groups(*groups)
    reused = evaluate_unit_groups(*groups, tracked=tracked)
    # then: the same figures, for groups that hold trials
    assert reused == replayed
    assert reused["same_unit"]["units"] == ["est-1"] and reused["new_calibrated"]["units"] == ["est-9"]
    assert reused["same_unit"]["external_trials"] == {angle_name(a): 2 for a in ANGLES}
    counts = reused["new_calibrated"]["results"]["ls"]["combined"]["confusion_final"]["counts"]
    assert np.sum(counts) == 2 * len(ANGLES)
