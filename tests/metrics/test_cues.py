"""The cues' headline figures in metrics.json, from a hand-made cue evaluation."""

from __future__ import annotations

import pytest

from needlecue_runtime.cues.pack import CUES, VERDICTS
from pipeline.cues.document import FORMAT, ScoredCues, SkippedCues
from pipeline.metrics.cues import cue_headline


def _result(balanced: float, wrong: float, counts: list[list[int]], group: bool = False) -> dict:
    """One method's result on its trials (`group`: the fields a unit group keeps)."""
    seen = {"wrong_final": wrong, "wrong_ever": 2 * wrong, "wrong_frames": wrong / 2, "coverage_frames": 0.9}
    confusion = {"rows_true": list(VERDICTS), "cols_cue": list(CUES), "counts": counts}
    recall = {"continue": balanced, "correct": balanced, "stop": balanced}
    kept = {
        "within_s": 3.0,
        "recall_within_s": recall,
        "balanced_within_s": balanced,
        "accuracy_final": balanced,
        "confusion_final": confusion,
        "seen": seen,
    }
    if group:
        return kept
    return {
        **kept,
        "confusion_frames": confusion,
        "accuracy_frames": balanced,
        "recall_final": recall,
        "time_to_cue": {},
        "force_alarm_trials": None,
    }


def _scored(results: dict, by_unit_group: dict) -> ScoredCues:
    return ScoredCues.model_validate(
        {
            "format": FORMAT,
            "kinds": ["lstm"],
            "presets_deg": [30.0],
            "results": results,
            "by_unit_group": by_unit_group,
            "reference": "the measured force",
            "true_angles_deg": [30.0],
            "external_trials": {"30": 10},
            "truth": "from the angles",
            "angle_estimate_at_insertion_end": None,
        }
    )


def test_headline_takes_the_combined_cue_per_kind_and_unit_group_in_percent() -> None:
    # given: an evaluation with every trial, and the new unit calibrated (no uncalibrated group)
    counts = [[0, 3, 0, 0, 1], [0, 0, 4, 0, 0], [0, 0, 0, 2, 0]]
    results = {
        "lstm": {"combined": _result(0.95, 0.01, counts), "paper": _result(0.5, 0.2, counts)},
        "reference": {"paper": _result(0.9, 0.0, counts)},
    }
    group = {
        "units": ["u9"],
        "external_trials": {"30": 4},
        "results": {"lstm": {"combined": _result(0.9, 0.02, counts, True)}},
    }
    evaluation = _scored(results, {"new_calibrated": group})
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
    skipped = {"format": FORMAT, "kinds": [], "presets_deg": [], "results": {}, "model_kinds_asked": ["ls"]}
    assert cue_headline(SkippedCues.model_validate({**skipped, "skipped": "no external trials"})) == {}
