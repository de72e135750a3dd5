"""Do a trial's two files record the same insertion? Decided against the batch's other trials.

The alignment's quality (`pipeline.signals.clock`, R² of the reference's changes explained by the
estimator's) is high on the simulator's rig, but a nonlinear sensor, a noisy one, or a motion with
few sharp events gives a low R² with the right files too; an absolute gate then throws away good
data. What only a wrong pairing does is make the trial's own reference explain its estimator stream
no better than references of other insertions do. So a trial below `resample.min_quality` is scored
against the references of up to `MAX_PEERS` other trials of its batch (the same sensor, the same
rig: what an unrelated reference gives on this data) and set aside only when

- another trial's reference explains it at least `SWAP_RATIO` times as well as its own (and by
  `MARGIN` more): files swapped; or
- its own reference is not clearly above what the others give (`MARGIN` over their median): the
  two files do not record one insertion.

Otherwise it is kept, with the figures in offsets.csv (`peer_quality`). With no other trial to
compare with, the absolute gate is all there is.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

MAX_PEERS = 8  # other references a low-quality trial is scored against (same angle first)
MARGIN = 0.1  # R² points the own reference must exceed the peers' median by (or a swap beat it by)
SWAP_RATIO = 2.0  # how many times the own R² another reference must reach to call the files swapped:
# with few, random events (a hand pressing a few times) one press of another trial can line up by
# chance and beat a noisy trial's own reference a little; a swapped file's true partner wins by far


@dataclass(frozen=True)
class Verdict:
    """What the batch says of one low-quality trial: `reason` to set it aside, or None to keep it;
    `best_peer` is the highest quality any other reference gave (None: no peer)."""

    reason: str | None
    best_peer: float | None


def peers_of(trial_id: str, angles: Mapping[str, str]) -> list[str]:
    """Up to MAX_PEERS other trials of the batch to compare with: those at the same angle first,
    then the rest, each group in trial order. `angles` maps every usable trial to its angle."""
    others = sorted(t for t in angles if t != trial_id)
    own_angle = angles.get(trial_id)
    same = [t for t in others if angles[t] == own_angle]
    rest = [t for t in others if angles[t] != own_angle]
    return (same + rest)[:MAX_PEERS]


def judge(own: float, peers: Mapping[str, float], min_quality: float) -> Verdict:
    """The verdict on a trial whose own alignment quality `own` is below `min_quality`, given the
    quality each peer's reference gives against its estimator stream."""
    if not peers:
        return Verdict(
            f"clock alignment quality {own:.2f} below resample.min_quality = {min_quality:g}, and no other "
            "trial in its batch to compare with: do the two files record the same insertion?",
            None,
        )
    best_id = max(sorted(peers), key=lambda t: peers[t])
    best = peers[best_id]
    median = float(np.median(list(peers.values())))
    if best >= max(own + MARGIN, SWAP_RATIO * own):
        return Verdict(
            f"the reference of trial {best_id} explains its estimator stream better ({best:.2f}) than its "
            f"own ({own:.2f}): reference files swapped?",
            best,
        )
    if own < median + MARGIN:
        return Verdict(
            f"clock alignment quality {own:.2f} below resample.min_quality = {min_quality:g} and no better "
            f"than other trials' references give (median {median:.2f} of {len(peers)}): do the two files "
            "record the same insertion?",
            best,
        )
    return Verdict(None, best)
