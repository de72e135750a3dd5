"""metrics.json: the headline figures a person compares across commits (`dvc metrics diff`, `dvc exp
show`), picked from the full evaluation (`reports/evaluation.json`, which the report and the
registry read). About thirty numbers, so that DVC's tables fit a terminal:

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
from collections.abc import Mapping
from typing import Any

from pipeline.metrics.scores import mean_known, mean_over_axes

TRANSFER = ("same_unit", "new_uncalibrated", "new_calibrated", "ratio")
CUE_GROUPS = ("same_unit", "new_calibrated")
CUE_FIGURES = ("balanced_within_s", "wrong_final", "wrong_frames", "coverage_frames")


def _nrmse(axes: Mapping[str, Any]) -> float | None:
    """Mean NRMSE of the axes of one (model, angle) entry of `within_angle`."""
    return mean_over_axes({a: (s or {}).get("nrmse_pct") for a, s in axes.items()})


def headline(evaluation: Mapping[str, Any]) -> dict[str, Any]:
    """The headline figures of a full evaluation (the evaluate stage's `compute_metrics` and the
    sections it adds); a section the evaluation lacks is left out, never filled with zeros."""
    within = evaluation.get("within_angle") or {}
    out: dict[str, Any] = {}
    per_kind = {kind: mean_known(_nrmse(axes) for axes in angles.values()) for kind, angles in within.items()}
    if per_kind:
        out["nrmse_pct"] = per_kind
    champions = ((evaluation.get("unit_transfer") or {}).get("champion") or {}).get("kinds") or {}
    if champions:
        out["champion_nrmse_pct"] = {
            a: _nrmse(within[k][a]) for a, k in champions.items() if a in within.get(k, {})
        }
    gaps = [str(g) for g in evaluation.get("gaps_deg") or []]
    curve = evaluation.get("gap_curve") or {}
    if gaps and curve:
        out["gap_nrmse_pct"] = {
            kind: {g: (by_gap.get(g) or {}).get("mean") for g in gaps} for kind, by_gap in curve.items()
        }
    transfer = (evaluation.get("unit_transfer") or {}).get("champion") or {}
    if any(k in transfer for k in TRANSFER):
        out["unit_transfer"] = {k: transfer.get(k) for k in TRANSFER}
    cues = evaluation.get("cues") or {}
    if cues and champions:
        kind = Counter(champions.values()).most_common(1)[0][0]  # the champions' kind at most angles
        groups = cues.get(kind) or {}
        out["cues"] = {
            g: {f: (groups.get(g) or {}).get(f) for f in CUE_FIGURES} for g in CUE_GROUPS if g in groups
        }
    return out
