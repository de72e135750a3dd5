"""The evaluation figures' choices."""

from __future__ import annotations

from pipeline.reporting.figures import gap_examples
from tests.metrics.fakes import ANGLES


def test_fig8_pairs_prefer_the_15_degree_model_and_fall_back():
    assert gap_examples(ANGLES, ANGLES, (15, 30)) == [("15", "30"), ("15", "45")]
    assert gap_examples(["0", "30", "60"], ["0", "30", "60"], (15, 30)) == [("0", "30")]
