"""The champion rule, as pure functions of scores and the registry's state (no MLflow here).

Per angle, the best deployable candidate is the one with the lowest mean external NRMSE (ties go
to the simpler kind). It takes the `champion` alias only if it beats the current champion,
re-scored on today's external set, by more than `min_improvement_pct`; else it is `challenger`.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

from needlecue_runtime.registry.store import CHALLENGER, CHAMPION
from pipeline.registry.candidates import Trained, kind_rank


def best_per_angle(trained: Iterable[Trained], candidates: tuple[str, ...]) -> dict[str, Trained]:
    """The champion rule's first half: per angle, the candidate with the lowest mean external NRMSE
    (ties go to the simpler model, in the order ls, fnn, lstm)."""
    best: dict[str, Trained] = {}
    for t in trained:
        if t.kind not in candidates or t.judged_on is None:
            continue
        cur = best.get(t.angle)
        if cur is None or (t.mean_nrmse(), kind_rank(t.kind)) < (cur.mean_nrmse(), kind_rank(cur.kind)):
            best[t.angle] = t
    return dict(sorted(best.items(), key=lambda kv: float(kv[0])))


@dataclass(frozen=True)
class Decision:
    """Which alias a newly registered version takes, and why."""

    promote: bool
    reason: str

    @property
    def alias(self) -> str:
        return CHAMPION if self.promote else CHALLENGER


def decide(
    score: float,
    champion_version: int | None,
    champion_score: float | None,
    min_improvement_pct: float,
    *,
    repack: bool = False,
) -> Decision:
    """The champion rule's second half. `score`: the new version's mean external NRMSE (%);
    `champion_version`: the current champion's version (None: there is none); `champion_score`: its
    mean NRMSE re-scored on the same external set (None: it cannot read today's data, so it cannot
    defend its title); `repack`: the new version is the champion's own model with a new cue pack or graph
    (the same force, new cues: it takes the champion's place, or the new cues would never reach a
    simulator)."""
    if champion_version is None:
        return Decision(True, "no champion yet")
    if repack:
        return Decision(
            True, f"champion v{champion_version}'s own model, packed anew (a new cue pack or graph)"
        )
    if champion_score is None:
        return Decision(True, f"champion v{champion_version} cannot be scored on today's external set")
    margin = champion_score - score
    return Decision(
        margin > min_improvement_pct,
        f"external NRMSE {score:.3f} % vs champion v{champion_version} {champion_score:.3f} % "
        f"({'better' if margin > 0 else 'not better'} by {abs(margin):.3f}, "
        f"needed > {min_improvement_pct:g})",
    )
