"""The champion rule as pure functions: the best candidate per angle, and which alias it takes."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from pipeline.registry.candidates import Trained
from pipeline.registry.champion import best_per_angle, decide


def trained(kind: str, angle: str, external: float, test: float = 50.0) -> Trained:
    """A candidate whose NRMSE is `external` (or NaN: no external rows) on every axis."""

    def scores(x: float) -> dict[str, dict[str, float]]:
        return {a: {"rmse": x / 100, "nrmse_pct": x} for a in ("fx", "fy", "fz")}

    return Trained(
        kind,
        angle,
        Path(kind, angle),
        f"sha-{kind}-{angle}",
        {},
        {},
        {"external": scores(external), "test": scores(test)},
    )


def test_best_per_angle_is_the_lowest_external_nrmse_among_candidates() -> None:
    # given: three kinds at two angles, the lstm best at 30° but not a candidate at 45°
    models = [
        trained("ls", "30", 9.0),
        trained("fnn", "30", 5.0),
        trained("lstm", "30", 4.0),
        trained("ls", "45", 8.0),
        trained("lstm", "45", 1.0),
    ]
    # when
    best = best_per_angle(models, ("ls", "fnn", "lstm"))
    only_ls = best_per_angle(models, ("ls",))
    # then
    assert {a: t.kind for a, t in best.items()} == {"30": "lstm", "45": "lstm"}
    assert {a: t.kind for a, t in only_ls.items()} == {"30": "ls", "45": "ls"}


def test_ties_go_to_the_simpler_kind_and_the_test_split_stands_in_for_a_missing_external_set() -> None:
    # given: an exact tie at 30°, and an angle whose external set is empty (NaN scores)
    models = [trained("lstm", "30", 5.0), trained("ls", "30", 5.0), trained("fnn", "60", math.nan, test=7.0)]
    # when
    best = best_per_angle(models, ("ls", "fnn", "lstm"))
    # then
    assert best["30"].kind == "ls"
    assert best["60"].judged_on == "test" and best["60"].mean_nrmse() == pytest.approx(7.0)


def test_decide_promotes_only_a_real_improvement() -> None:
    # no champion yet, or one that cannot read today's data: the newcomer takes the title
    assert decide(5.0, None, None, 0.0).alias == "champion"
    assert "no champion yet" in decide(5.0, None, None, 0.0).reason
    unscorable = decide(5.0, 3, None, 0.0)
    assert unscorable.promote and "v3 cannot be scored" in unscorable.reason
    # better by more than the margin: champion; equal or not better enough: challenger
    assert decide(4.0, 2, 5.0, 0.5).alias == "champion"
    assert decide(5.0, 2, 5.0, 0.0).alias == "challenger"
    not_enough = decide(4.8, 2, 5.0, 0.5)
    assert not not_enough.promote and "better by 0.200, needed > 0.5" in not_enough.reason
    assert "not better" in decide(6.0, 2, 5.0, 0.0).reason


def test_decide_gives_the_champions_own_model_with_a_new_cue_pack_the_title() -> None:
    # given: the champion v2's model, re-registered with a new cue pack (same force, new cues)
    # when / then: it takes the champion's place whatever the scores, and says why
    repacked = decide(5.0, 2, 5.0, 0.0, repack=True)
    assert repacked.alias == "champion" and "v2's own model, packed anew" in repacked.reason
