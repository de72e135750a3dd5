"""The report's `## How much data you need` section and its figure, rendered from a needs document."""

from __future__ import annotations

import copy
from pathlib import Path

from pipeline.reporting.needs import how_much_data_you_need, plot_needs
from tests.needs.docs import needs_doc, typed

PNG = b"\x89PNG\r\n\x1a\n"


def test_the_section_shows_the_advice_the_tables_and_the_figure() -> None:
    # given / when
    text = how_much_data_you_need(typed(needs_doc()))
    # then: the heading, the advice, a row per ladder step with force and cue figures, the calibration
    # rows, what was not computed, the figure linked relative to reports/
    assert text.startswith("## How much data you need\n")
    assert "- The cues do not reach 95 % with the 12 you have." in text
    assert "| 12 | 24 (12, 12) | 7.30 | 5.90 | 93.0 % | 1.0 % | 0.5 % | 80.0 % |" in text
    assert "| **mean of 2 left out** | 2 |  | 80.0 % |" in text
    assert "| N (new unit) | 1 | 126 | 90.0 % |" in text
    assert "- N with 2 calibration insertions per angle: its batch has 1" in text
    assert "Force against calibration insertions is not recomputed" in text
    assert text.rstrip().endswith("(needs/needs.png)")


def test_a_step_that_was_not_scored_says_why_in_its_row() -> None:
    # given: the first step's cues not scored
    doc = needs_doc()
    doc["training"]["steps"][0]["cues"] = {"unavailable": "no angle estimator could be fitted"}
    # when / then
    assert "| 6 | 12 (6, 6) | 7.30 | 5.90 | not scored: no angle estimator could be fitted |" in (
        how_much_data_you_need(typed(doc))
    )


def test_the_figure_has_the_same_bytes_every_time(tmp_path: Path) -> None:
    # given / when: the figure drawn twice
    for name in ("a.png", "b.png"):
        plot_needs(typed(needs_doc()), tmp_path / name)
    # then
    first = (tmp_path / "a.png").read_bytes()
    assert first[:8] == PNG and first == (tmp_path / "b.png").read_bytes()


def test_the_figure_of_a_document_with_nothing_computed_still_draws(tmp_path: Path) -> None:
    # given: no force model, no scored cue, no calibration curve
    doc = copy.deepcopy(needs_doc())
    doc["training"]["force_models"] = []
    for step in doc["training"]["steps"]:
        step["cues"] = {"unavailable": "no external trial of a training unit"}
    doc["calibration"].update(new_units={}, leave_one_unit_out=None)
    # when
    plot_needs(typed(doc), tmp_path / "needs.png")
    # then: a PNG, and the section has no calibration table
    assert (tmp_path / "needs.png").read_bytes()[:8] == PNG
    assert "### Calibration insertions per angle" not in how_much_data_you_need(typed(doc))
