"""The cues' headline figures in evaluation.json (the headline of that in metrics.json): what a trainee
sees, per model kind and unit group,
from the cues stage's evaluation.json (`pipeline.cues.score`), our combined cue only."""

from __future__ import annotations

from typing import Any

from pipeline.cues.document import CueEvaluation, SkippedCues

SEEN = ("wrong_final", "wrong_ever", "wrong_frames", "coverage_frames")
GROUPS = ("all", "same_unit", "new_uncalibrated", "new_calibrated")


def cue_headline(evaluation: CueEvaluation | None) -> dict[str, Any]:
    """{kind: {group: {"balanced_within_s", "wrong_final", "wrong_ever", "wrong_frames",
    "coverage_frames", "trials"}}} of the combined cue, in percent: "all" is every external trial,
    the others `by_unit_group`'s groups; a group without trials is left out. Empty without an
    evaluation or a scored combined cue."""
    if evaluation is None or isinstance(evaluation, SkippedCues):
        return {}
    groups: dict[str, Any] = {"all": evaluation.results}
    for g, d in (evaluation.by_unit_group or {}).items():
        groups[g] = d.results
    out: dict[str, Any] = {}
    for group in GROUPS:
        for kind, methods in groups.get(group, {}).items():
            r = methods.get("combined")
            if r is None:
                continue
            out.setdefault(kind, {})[group] = {
                "balanced_within_s": _pct(r.balanced_within_s),
                **{k: _pct(getattr(r.seen, k)) for k in SEEN},
                "trials": int(sum(map(sum, r.confusion_final.counts))),
            }
    return out


def _pct(x: float | None) -> float | None:
    return None if x is None else 100.0 * float(x)
