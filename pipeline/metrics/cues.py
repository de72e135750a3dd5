"""The cues' headline figures in evaluation.json (the headline of that in metrics.json): what a trainee
sees, per model kind and unit group,
from the cues stage's evaluation.json (`pipeline.cues.score`), our combined cue only."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

SEEN = ("wrong_final", "wrong_ever", "wrong_frames", "coverage_frames")
GROUPS = ("all", "same_unit", "new_uncalibrated", "new_calibrated")


def cue_headline(evaluation: Mapping[str, Any] | None) -> dict[str, Any]:
    """{kind: {group: {"balanced_within_s", "wrong_final", "wrong_ever", "wrong_frames",
    "coverage_frames", "trials"}}} of the combined cue, in percent: "all" is every external trial,
    the others `by_unit_group`'s groups; a group without trials is left out. Empty without an
    evaluation or a scored combined cue."""
    if not evaluation or evaluation.get("skipped"):
        return {}
    groups = {"all": evaluation.get("results") or {}}
    for g, d in (evaluation.get("by_unit_group") or {}).items():
        groups[g] = d.get("results") or {}
    out: dict[str, Any] = {}
    for group in GROUPS:
        for kind, methods in groups.get(group, {}).items():
            r = methods.get("combined")
            if r is None:
                continue
            seen = r.get("seen") or {}
            counts = (r.get("confusion_final") or {}).get("counts") or []
            out.setdefault(kind, {})[group] = {
                "balanced_within_s": _pct(r.get("balanced_within_s")),
                **{k: _pct(seen.get(k)) for k in SEEN},
                "trials": int(sum(map(sum, counts))),
            }
    return out


def _pct(x: float | None) -> float | None:
    return None if x is None else 100.0 * float(x)
