"""The cue figures a needs step keeps of a cue evaluation."""

from __future__ import annotations

from pipeline.needs.scoring import cue_figures


def test_cue_figures_of_an_evaluation_that_scored_nothing_say_why() -> None:
    # given: a skipped evaluation / when / then
    assert cue_figures({"skipped": "no external trials", "results": {}}) == {
        "unavailable": "no external trials"
    }
