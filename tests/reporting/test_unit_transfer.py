"""The report's "Estimator units" section speaks of the data at hand: every figure from this run's
metrics, and a figure the data cannot give reads as missing, with what it would need."""

from __future__ import annotations

import re

from pipeline.metrics.document import Evaluation
from pipeline.reporting.unit_transfer import estimator_units
from tests.metrics.documents import evaluation

SCORES = {"same_unit": 4.0, "new_uncalibrated": 5.0, "new_calibrated": 4.4}


def _metrics(**groups: float | None) -> Evaluation:
    row = {**SCORES, **groups}
    same, new = row["same_unit"], row["new_calibrated"]
    row["ratio"] = None if same is None or new is None else new / same
    worse = {k: (None if v is None else v + 1.0) for k, v in row.items() if k != "ratio"}
    transfer = {"ls": {**worse, "ratio": None}, "fnn": dict(row), "champion": dict(row)}
    return evaluation(unit_transfer=transfer)


def test_the_targets_give_this_runs_figures():
    # Given a run whose champion scores 4.0 % on its training units and 4.4 % on the new unit
    text = estimator_units(_metrics(), None)
    # Then the section quotes them and their ratio, judged against the targets
    assert "champion NRMSE 4.00 %; the best one kind of model at every angle, FNN, 4.00 %" in text
    assert "at most 1.2× the same-unit figure: 1.10× ✓" in text
    assert (
        "without its calibration, champion NRMSE (reported; at most 1.5× where the front end is declared): "
        "1.25×" in text
    )
    # and no figure of the built-in simulator's from before units existed
    assert "3.2 %" not in text and "before units" not in text


def test_a_lab_without_same_unit_external_trials_reads_missing_not_a_bare_unit():
    # Given a lab whose held-out batches are all from a new unit
    text = estimator_units(_metrics(same_unit=None), None)
    # Then what cannot be computed says so and why, and no line ends in a unit without a number
    assert "champion NRMSE missing (no external trial of a training unit)" in text
    assert "the same-unit figure: missing (no external trial of a training unit)" in text
    assert "missing (no cue scored on a calibrated new unit's external trials)" in text
    assert not re.search(r":\s*(×|%)", text)


def test_a_lab_without_a_calibrated_new_unit_reads_missing():
    text = estimator_units(_metrics(new_calibrated=None, new_uncalibrated=None), None)
    assert "the same-unit figure: missing (no external trial of a new unit with a calibration)" in text
    assert "missing (no cue scored on a calibrated new unit's external trials)" in text
