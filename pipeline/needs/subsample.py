"""Which training insertions a smaller lab would have had: subsamples of each angle's training trials,
spread evenly over the units and their batches and seeded, and the ladder of counts to try."""

from __future__ import annotations

import zlib
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import numpy as np
import pandas as pd

FIRST_STEP = 3  # "auto": the ladder doubles from here
Key = tuple[str, str]  # a trial: (batch_id, trial_id)
Selection = dict[float, list[Key]]  # {angle: trials}
SUBSAMPLE = (
    "per angle, the training trials in turn over the units, each unit's turn over its batches (units and "
    "angles starting at other batches), the trials of a batch in a seeded random order; a count takes "
    "the first that many, so a larger count's subsample holds a smaller one's"
)


def units_of(frame: pd.DataFrame) -> pd.Series:
    """Each row's unit id as text ("" where the frame has no unit_id column)."""
    if "unit_id" not in frame.columns:
        return pd.Series("", index=frame.index)
    return frame["unit_id"].astype(str)


def trials_in(frame: pd.DataFrame) -> list[tuple[str, Key]]:
    """Every trial of a frame once, as (unit, (batch_id, trial_id)), sorted."""
    cols = zip(units_of(frame), frame["batch_id"].astype(str), frame["trial_id"].astype(str), strict=True)
    return sorted({(u, (b, t)) for u, b, t in cols})


def select(frame: pd.DataFrame, keys: Iterable[Key]) -> pd.DataFrame:
    """The rows of the trials `keys`, in the frame's order."""
    wanted = set(keys)
    pairs = zip(frame["batch_id"].astype(str), frame["trial_id"].astype(str), strict=True)
    return frame[[k in wanted for k in pairs]].reset_index(drop=True)


def _round_robin(queues: Sequence[Sequence[Any]]) -> list[Any]:
    """The first of each queue, then the second of each, ...; a queue that runs out is skipped."""
    return [q[r] for r in range(max(map(len, queues), default=0)) for q in queues if r < len(q)]


def spread_order(trials: Sequence[tuple[str, Key]], seed: int, salt: str, start: int = 0) -> list[Key]:
    """Every trial once, in the order a subsample takes them (`SUBSAMPLE`): the first n are spread as
    evenly as n allows over the units and, within each unit, over its batches. `salt` (the angle)
    gives each angle its own draw from `seed`; `start` (the angle's index) moves the unit that comes
    first and each unit's first batch, so that over the angles they take turns."""
    rng = np.random.default_rng(zlib.crc32(f"{seed}/{salt}".encode()))
    by_unit: dict[str, dict[str, list[Key]]] = {}
    for unit, key in sorted(set(trials)):
        by_unit.setdefault(unit, {}).setdefault(key[0], []).append(key)
    queues = []
    for i, unit in enumerate(sorted(by_unit)):
        batches = sorted(by_unit[unit])
        # each unit, and each angle, starts at another batch: with casts named in the same order, the
        # first insertions come from other casts
        turn = (i + start) % len(batches)
        shuffled = [[by_unit[unit][b][j] for j in rng.permutation(len(by_unit[unit][b]))] for b in batches]
        queues.append(_round_robin(shuffled[turn:] + shuffled[:turn]))
    first = start % len(queues) if queues else 0
    return _round_robin(queues[first:] + queues[:first])


def ladder(have: Mapping[float, int], asked: str | Sequence[int]) -> tuple[list[int], list[dict[str, str]]]:
    """(training insertions per angle to try, what was asked and cannot be): for "auto", FIRST_STEP
    doubled while every angle has more, then what every angle has; else the counts asked that every
    angle has (what every angle has, if none is)."""
    fewest = min(have.values())
    if asked == "auto":
        steps, n = [], FIRST_STEP
        while n < fewest:
            steps.append(n)
            n *= 2
        return [*steps, fewest], []
    steps = [n for n in asked if n <= fewest]
    over = [n for n in asked if n > fewest]
    why = f"the fewest of any angle is {fewest}"
    notes = [{"what": f"{n} training insertions per angle", "why": why} for n in over]
    return steps or [fewest], notes
