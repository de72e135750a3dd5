"""Whole evaluation documents for the tests: every section present, empty unless given."""

from __future__ import annotations

from typing import Any

from pipeline.metrics.document import Evaluation

LISTS = ("gaps_deg", "models_evaluated")


def evaluation(**sections: Any) -> Evaluation:
    """An `Evaluation` holding `sections` (e.g. `compute_metrics`' output), every other one empty."""
    empty = {name: [] if name in LISTS else {} for name in Evaluation.model_fields}
    return Evaluation.model_validate({**empty, **sections})
