"""Whole needs documents, as the needs stage writes them (`pipeline.needs.document`), for the advice,
the report's section and the document's own tests."""

from __future__ import annotations

from typing import Any

from pipeline.needs.document import NEEDS_DOC, Needs

PARAMS = {"training_insertions": "auto", "calibration_insertions": [1, 2], "cue_target_pct": 95.0, "seed": 0}


def cues(balanced: float, coverage: float) -> dict[str, Any]:
    """Scored cue figures."""
    seen = {"wrong_final": 0.01, "wrong_frames": 0.005, "coverage_frames": coverage}
    recall = {"continue": balanced, "correct": balanced, "stop": balanced}
    return {"balanced_within_s": balanced, "recall_within_s": recall, "seen": seen, "trials": 126}


def step(per_angle: int, figures: dict[str, Any] | None, force: dict[str, float]) -> dict[str, Any]:
    """One ladder step of two units, one batch, with each force curve's mean NRMSE %."""
    return {
        "per_angle": per_angle,
        "trials": 2 * per_angle,
        "by_unit": {"A": per_angle, "B": per_angle},
        "batches": 1,
        "force": {n: {"mean_nrmse_pct": v, "by_angle": {"0": v, "15": v}} for n, v in force.items()},
        "cues": figures,
    }


def needs_doc() -> dict[str, Any]:
    """A needs document: two ladder steps, two units left out, one new unit."""
    force = {"ls": 7.3, "fnn_stand_in": 5.9}
    return {
        "format": "needlecue-needs/1",
        "params": PARAMS,
        "cue_within_s": 3.0,
        "training": {
            "have_per_angle": {"0": 12, "15": 12},
            "units": ["A", "B"],
            "ladder": [6, 12],
            "subsample": "spread over units and batches",
            "force_models": [
                {"name": "ls", "about": "LS on rest_volts"},
                {"name": "fnn_stand_in", "about": "ridge"},
            ],
            "force_scored_on": "held-out trials",
            "cues_scored_on": "held-out trials",
            "steps": [step(6, cues(0.81, 0.7), force), step(12, cues(0.93, 0.8), force)],
        },
        "calibration": {
            "insertions_per_angle": [1, 2],
            "force": "not recomputed: it needs the models retrained without the unit",
            "new_units": {
                "N": {"calibration_insertions": {"0": 1, "15": 1}, "steps": [{"k": 1, **cues(0.9, 0.8)}]}
            },
            "leave_one_unit_out": {
                "units": {
                    u: {"test_trials": 30, "steps": [{"k": 1, **cues(0.7, 0.6)}, {"k": 2, **cues(0.8, 0.7)}]}
                    for u in "AB"
                },
                "mean": [
                    {
                        "k": 1,
                        "units": 2,
                        **{k: v for k, v in cues(0.7, 0.6).items() if k in ("balanced_within_s", "seen")},
                    },
                    {
                        "k": 2,
                        "units": 2,
                        **{k: v for k, v in cues(0.8, 0.7).items() if k in ("balanced_within_s", "seen")},
                    },
                ],
            },
        },
        "advice": ["The cues do not reach 95 % with the 12 you have."],
        "not_computed": [{"what": "N with 2 calibration insertions per angle", "why": "its batch has 1"}],
    }


def typed(doc: dict[str, Any]) -> Needs:
    """`doc` as the reader gives it."""
    return NEEDS_DOC.adapter.validate_python(doc)
