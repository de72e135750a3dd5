"""Subsamples of a lab's training insertions: seeded, every trial once, spread evenly over units and
batches, nested; the ladder of counts to try."""

from __future__ import annotations

from collections import Counter

import pytest

from pipeline.needs.subsample import ladder, spread_order


def trials(units: int, batches: int, per_batch: int) -> list[tuple[str, tuple[str, str]]]:
    return [
        (f"u{u}", (f"u{u}-b{b}", f"t{k}"))
        for u in range(units)
        for b in range(batches)
        for k in range(per_batch)
    ]


def test_the_subsample_order_is_seeded_and_takes_every_trial_once() -> None:
    # given: 3 units x 2 batches x 4 trials
    given = trials(3, 2, 4)
    # when: ordering them twice with one seed, and once with another
    first, again, other = (spread_order(given, s, "30") for s in (0, 0, 1))
    # then: the same order for the same seed, another for another seed, every trial exactly once
    assert first == again
    assert first != other
    assert sorted(first) == sorted(k for _, k in given)


@pytest.mark.parametrize(("units", "batches", "per_batch"), [(3, 3, 3), (2, 3, 2), (3, 2, 1)])
def test_every_subsample_is_spread_evenly_over_units_and_their_batches(
    units: int, batches: int, per_batch: int
) -> None:
    # given: a lab's trials of one angle
    given = trials(units, batches, per_batch)
    owner = dict((k, u) for u, k in given)
    order = spread_order(given, 7, "45")
    for n in range(1, len(order) + 1):
        # when: taking the first n
        taken = order[:n]
        # then: no unit has more than one trial over another, nor any unit's batch over its other batches
        per_unit = Counter(owner[k] for k in taken)
        assert max(per_unit.values()) - min(per_unit.get(f"u{u}", 0) for u in range(units)) <= 1
        for u in range(units):
            per_batch_of_u = Counter(k[0] for k in taken if owner[k] == f"u{u}")
            counts = [per_batch_of_u.get(f"u{u}-b{b}", 0) for b in range(batches)]
            assert max(counts) - min(counts) <= 1


def test_units_and_angles_start_at_different_units_and_casts() -> None:
    # given: 3 units with the same 3 batch names in the same order (casts recorded by every unit)
    given = [(u, (f"cast{b}-{u}", f"t{k}")) for u in "abc" for b in range(3) for k in range(2)]
    # when: ordering them for the angles of index 0, 1 and 2
    firsts = [spread_order(given, 0, "15", i)[:3] for i in range(3)]
    # then: at each angle the first three are one per unit from three different casts, the next angle's
    # turn starts at the next unit, and over the three angles each unit's first insertion is from each cast
    assert [k[0] for k in firsts[0]] == ["cast0-a", "cast1-b", "cast2-c"]
    assert [k[0] for k in firsts[1]] == ["cast2-b", "cast0-c", "cast1-a"]
    for unit in "abc":
        casts = {k[0] for first in firsts for k in first if k[0].endswith(unit)}
        assert casts == {f"cast{b}-{unit}" for b in range(3)}


def test_the_auto_ladder_doubles_from_3_and_ends_at_what_every_angle_has() -> None:
    # given / when / then: doubling while every angle has more, then the fewest count of any angle
    assert ladder({15.0: 23, 30.0: 25}, "auto") == ([3, 6, 12, 23], [])
    assert ladder({15.0: 24}, "auto") == ([3, 6, 12, 24], [])
    assert ladder({15.0: 2}, "auto") == ([2], [])


def test_a_ladder_asked_for_keeps_what_every_angle_has_and_says_what_it_drops() -> None:
    # given: counts asked for, one more than an angle has
    steps, notes = ladder({15.0: 10, 30.0: 12}, (2, 4, 11))
    # then: 11 is dropped, saying the fewest of any angle
    assert steps == [2, 4]
    assert notes == [{"what": "11 training insertions per angle", "why": "the fewest of any angle is 10"}]
    # and a ladder with nothing left falls back to the fewest
    assert ladder({15.0: 3}, (5, 8))[0] == [3]
