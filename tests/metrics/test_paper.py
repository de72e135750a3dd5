"""The paper's findings as checks, run on the paper's own numbers."""

from __future__ import annotations

from pipeline.metrics.paper import (
    PAPER_TABLE3,
    TABLE3_KINDS,
    check_fnn_beats_lstm_at,
    check_fnn_beats_lstm_gap,
    check_gap_growth,
    check_ls_worse,
    paper_metrics,
)


def test_the_paper_side_is_computed_from_the_paper_tables():
    paper = paper_metrics()
    assert check_ls_worse(paper).holds is True
    assert check_gap_growth(paper, "fnn").text.startswith("FNN: 8.13% (0°) → 15.64% (15°) → 35.29% (30°)")
    assert check_fnn_beats_lstm_at(paper, "30").holds is True
    assert check_fnn_beats_lstm_gap(paper, "15").holds is False


def test_table_3_compares_the_kinds_the_papers_table_3_does():
    # given / when / then: its kinds are those of the paper's Table III, in its row order
    assert TABLE3_KINDS == ("lstm", "fnn")
    assert {kind for kind, _ in PAPER_TABLE3} == set(TABLE3_KINDS)
