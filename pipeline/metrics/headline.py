"""metrics.json: the headline figures a person compares across commits (`dvc metrics diff`, `dvc exp
show`), picked from the full evaluation (`reports/evaluation.json`, `pipeline.metrics.document`,
which the report and the registry read). About thirty numbers, so that DVC's tables fit a terminal:

- `nrmse_pct.<kind>`: each model kind's within-angle NRMSE on the external sets, mean of the axes
  and angles;
- `champion_nrmse_pct.<angle>`: the best kind's at each angle;
- `gap_nrmse_pct.<kind>.<gap>`: mean NRMSE of a model on data an angle gap away;
- `unit_transfer`: the champion's NRMSE on the same unit, on a new unit uncalibrated and calibrated,
  and calibrated over same;
- `cues.<group>`: what a trainee sees on the same unit and on a new calibrated unit, with the cues of
  the kind that is champion at most angles: balanced accuracy within the cue time, wrong cues at the
  end of an insertion and per frame, and coverage (%).
"""

from __future__ import annotations

from collections import Counter
from typing import Any

from pipeline.metrics.document import Evaluation, Scores
from pipeline.metrics.scores import mean_known, mean_over_axes

TRANSFER = ("same_unit", "new_uncalibrated", "new_calibrated", "ratio")
CUE_GROUPS = ("same_unit", "new_calibrated")
CUE_FIGURES = ("balanced_within_s", "wrong_final", "wrong_frames", "coverage_frames")


def _nrmse(scores: Scores) -> float | None:
    """Mean NRMSE of the axes of one (model, angle) entry of `within_angle`."""
    return mean_over_axes({a: s.nrmse_pct for a, s in scores.items()})


def headline(evaluation: Evaluation) -> dict[str, Any]:
    """The headline figures of a full evaluation; a section with nothing in it (no model, no
    champion, no cue evaluation) is left out, never filled with zeros."""
    within = evaluation.within_angle
    out: dict[str, Any] = {}
    per_kind = {kind: mean_known(_nrmse(axes) for axes in angles.values()) for kind, angles in within.items()}
    if per_kind:
        out["nrmse_pct"] = per_kind
    champion = evaluation.unit_transfer.get("champion")
    champions = (champion.kinds if champion is not None else None) or {}
    if champions:
        out["champion_nrmse_pct"] = {
            a: _nrmse(within[k][a]) for a, k in champions.items() if a in within.get(k, {})
        }
    gaps, curve = evaluation.gaps_deg, evaluation.gap_curve
    if gaps and curve:
        out["gap_nrmse_pct"] = {
            kind: {g: by_gap[g].mean if g in by_gap else None for g in gaps} for kind, by_gap in curve.items()
        }
    if champion is not None:
        out["unit_transfer"] = {k: getattr(champion, k) for k in TRANSFER}
    if evaluation.cues and champions:
        kind = Counter(champions.values()).most_common(1)[0][0]  # the champions' kind at most angles
        groups = evaluation.cues.get(kind) or {}
        out["cues"] = {g: {f: getattr(groups[g], f) for f in CUE_FIGURES} for g in CUE_GROUPS if g in groups}
    return out
