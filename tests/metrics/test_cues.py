"""The cues' headline figures in metrics.json, from a hand-made cue evaluation."""

from __future__ import annotations

import pytest

from pipeline.metrics.cues import cue_headline


def _result(balanced: float, wrong: float, counts: list[list[int]]) -> dict:
    seen = {"wrong_final": wrong, "wrong_ever": 2 * wrong, "wrong_frames": wrong / 2, "coverage_frames": 0.9}
    return {"balanced_within_s": balanced, "seen": seen, "confusion_final": {"counts": counts}}


def test_headline_takes_the_combined_cue_per_kind_and_unit_group_in_percent() -> None:
    # given: an evaluation with every trial, and the new unit calibrated (no uncalibrated group)
    counts = [[0, 3, 0, 0, 1], [0, 0, 4, 0, 0], [0, 0, 0, 2, 0]]
    evaluation = {
        "results": {
            "lstm": {"combined": _result(0.95, 0.01, counts), "paper": _result(0.5, 0.2, counts)},
            "reference": {"paper": _result(0.9, 0.0, counts)},
        },
        "by_unit_group": {"new_calibrated": {"results": {"lstm": {"combined": _result(0.9, 0.02, counts)}}}},
    }
    # when
    out = cue_headline(evaluation)
    # then: the combined cue only (not the paper's method, not the reference bound), in percent
    assert set(out) == {"lstm"} and set(out["lstm"]) == {"all", "new_calibrated"}
    assert out["lstm"]["all"] == pytest.approx(
        {
            "balanced_within_s": 95.0,
            "wrong_final": 1.0,
            "wrong_ever": 2.0,
            "wrong_frames": 0.5,
            "coverage_frames": 90.0,
            "trials": 10,
        }
    )
    assert out["lstm"]["new_calibrated"]["wrong_final"] == pytest.approx(2.0)


def test_no_figures_without_a_scored_evaluation() -> None:
    assert cue_headline(None) == {}
    assert cue_headline({"skipped": "no external trials", "results": {}}) == {}
