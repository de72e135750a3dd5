"""Do a trial's two files record the same insertion? Decided on evidence, never on quality alone.

The alignment's quality (`pipeline.signals.clock`, R² of the reference's changes explained by the
estimator's) is high on the simulator's rig, but a nonlinear, hysteretic or noisy sensor, or a
repeated-press motion, gives a low R² with the right files, and then any other insertion's
reference explains a little of it too: neither an absolute gate nor "no better than the others"
shows that anything is wrong. So a trial below `resample.min_quality` is set aside for its pairing
only when something shows the files disagree:

- its own reference fits it clearly better (`SWAP_RATIO` times and by `MARGIN`) at an offset
  outside the search window than inside it: a shifted clock (`Shift`, searched up to `WIDE_FACTOR`
  times wider); on one clock (`reference.clock: shared`), also both files' ends displaced alike
  beyond the window (`stamps_shifted`). A steady, periodic motion fits itself a period away, so
  there a shift inside a period is told by the stamps alone; or
- another trial's reference of its batch (up to `MAX_PEERS`, same angle first) fits it clearly
  better than its own: reference files swapped.

(No overlap of the stamps, or a best offset at the window's edge, is set aside where the offset is
estimated.) Otherwise it is kept and flagged: offsets.csv, the ledger and the report say so, and
the models' validation shows whether it hurts.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

MAX_PEERS = 8  # other references a low-quality trial is scored against (same angle first)
MARGIN = 0.1  # R² points the own reference must exceed the peers' median by (or a swap beat it by)
WIDE_FACTOR = 10.0  # a low-quality trial's own reference is searched this many times wider (see Shift)
STAMP_AGREEMENT = 0.1  # share of a trial's span within which both ends' displacements must agree
SWAP_RATIO = 2.0  # how many times the own R² another reference must reach to call the files swapped:
# with few, random events (a hand pressing a few times) one press of another trial can line up by
# chance and beat a noisy trial's own reference a little; a swapped file's true partner wins by far


@dataclass(frozen=True)
class Verdict:
    """What the evidence says of one low-quality trial: `reason` to set it aside, or None to keep
    it with `flag` saying why it was looked at; `best_peer` is the highest quality any other
    reference gave (None: no peer)."""

    reason: str | None
    best_peer: float | None
    flag: str | None = None


@dataclass(frozen=True)
class Shift:
    """The trial's own reference searched over a wider window: the best quality inside the usual
    window (`inside`) and outside it (`outside`, at `offset_s`), on the same samples."""

    offset_s: float
    outside: float
    inside: float
    window_s: float  # the usual search window, ±


def clearly_better(other: float, own: float) -> bool:
    """Whether a fit of quality `other` beats `own` by enough to be evidence, not chance."""
    return other >= max(own + MARGIN, SWAP_RATIO * own)


def peers_of(trial_id: str, angles: Mapping[str, str]) -> list[str]:
    """Up to MAX_PEERS other trials of the batch to compare with: those at the same angle first,
    then the rest, each group in trial order. `angles` maps every usable trial to its angle."""
    others = sorted(t for t in angles if t != trial_id)
    own_angle = angles.get(trial_id)
    same = [t for t in others if angles[t] == own_angle]
    rest = [t for t in others if angles[t] != own_angle]
    return (same + rest)[:MAX_PEERS]


def stamps_shifted(fsr_s: tuple[float, float], ref_s: tuple[float, float], window_s: float) -> str | None:
    """On one clock (`reference.clock: shared`), a trial's two files cut from one recording start
    and end together; both ends displaced alike, by more than the search window, is a shifted clock
    (the reason), whatever the signals say. None: the stamps show no such shift."""
    start, end = ref_s[0] - fsr_s[0], ref_s[1] - fsr_s[1]
    span = max(fsr_s[1] - fsr_s[0], 1e-9)
    if min(abs(start), abs(end)) <= window_s or start * end <= 0 or abs(start - end) > STAMP_AGREEMENT * span:
        return None
    return (
        f"shifted clock: reference.clock: shared, but the reference is stamped {start:+.2f} s from the "
        f"estimator at its start and {end:+.2f} s at its end (more than ±{window_s:g} s); fix the stamps"
    )


def shifted(shift: Shift, *, shared: bool) -> str:
    """The reason a trial is set aside for a clock shifted beyond the search window."""
    claim = "reference.clock: shared says 0 s" if shared else f"the search covers ±{shift.window_s:g} s"
    return (
        f"shifted clock: its own reference fits best at an offset of {shift.offset_s:+.2f} s (quality "
        f"{shift.outside:.2f}, against {shift.inside:.2f} within ±{shift.window_s:g} s), but {claim}; "
        "fix the stamps or widen resample.max_offset_s"
    )


def judge(
    own: float,
    peers: Mapping[str, float],
    min_quality: float,
    shift: Shift | None = None,
    *,
    shared: bool = False,
) -> Verdict:
    """The verdict on a trial whose own alignment quality `own` is below `min_quality`, given the
    quality each peer's reference gives against its estimator stream and its own reference searched
    wider (`shift`; `shared`: batch.yaml says one clock stamped both streams)."""
    best_id = max(sorted(peers), key=lambda t: peers[t]) if peers else None
    best = peers[best_id] if best_id is not None else -1.0
    moved = shift is not None and clearly_better(shift.outside, shift.inside)
    # the better of the two explanations wins: another file, or its own file at another offset
    if best_id is not None and clearly_better(best, own) and not (moved and shift.outside > best):
        return Verdict(
            f"the reference of trial {best_id} explains its estimator stream better ({best:.2f}) than its "
            f"own ({own:.2f}): reference files swapped?",
            best,
        )
    if shift is not None and moved and shift.outside > best:
        return Verdict(shifted(shift, shared=shared), best if best_id is not None else None)
    compared = (
        f"no other trial's reference fits it better (best of {len(peers)}: {best:.2f})"
        if best_id is not None
        else "no other trial in its batch to compare with"
    )
    return Verdict(
        None,
        best if best_id is not None else None,
        f"alignment quality {own:.2f} below resample.min_quality = {min_quality:g}; kept: {compared}, "
        "nor its own reference at another offset",
    )
