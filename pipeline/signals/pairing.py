"""Do a trial's two files record the same insertion? Decided on evidence, never on quality alone.

The alignment's quality (`pipeline.signals.clock`, R² of the reference's changes explained by the
estimator's) is high on the simulator's rig, but a nonlinear, hysteretic or noisy sensor, or a
repeated-press motion, gives a low R² with the right files, and then any other insertion's
reference explains a little of it too: neither an absolute gate nor "no better than the others"
shows that anything is wrong. So a trial is set aside for its pairing only on evidence that its
files disagree:

- one of its streams is another trial's: the same values, whatever its stamps (the same, shifted or
  re-timed); the trial its own files fit worse is set aside naming the other (`copied`), whatever
  `resample.max_offset_s` is, before any clock is judged (a copy re-timed by a second would
  otherwise pass for a shifted clock, and widening the window would let it in);
- below `resample.min_quality`, another trial's reference of its batch (up to `MAX_PEERS`, same
  angle first) fits it clearly better than its own (`SWAP_RATIO` times and by `MARGIN`), or better
  by `MARGIN` while that trial is set aside as swapped with this one (`mutual_swaps`): swapped files;
- below `resample.min_quality`, its own reference fits it clearly better outside the search window
  than inside it, and well (`SHIFT_FLOOR`; searched up to `WIDE_FACTOR` times wider): a shifted
  clock. On one clock (`reference.clock: shared`) also a reference stamped alike late or early at
  both ends where the batch's other trials' files start and end together (`stamps_shifted`), or
  one that fits clearly better off 0 at a lag apart from the lag every other trial of the batch
  fits best at (`lag_off_the_batch`: a sensor's own lag is the same in every trial). A steady,
  periodic motion fits itself a period away: there a shift beyond the window is told by the stamps
  alone.

(No overlap of the stamps, or a best offset at the window's edge, is set aside where the offset is
estimated.) Otherwise a low-quality trial is kept and flagged: offsets.csv, the ledger and the
report say so, and the models' validation shows whether it hurts.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

MAX_PEERS = 8  # other references a low-quality trial is scored against (same angle first)
MARGIN = 0.1  # R² points the own reference must exceed the peers' median by (or a swap beat it by)
WIDE_FACTOR = 10.0  # a low-quality trial's own reference is searched this many times wider (see Shift)
LAG_TOLERANCE_S = 0.1  # on one clock, how far one trial's best lag may sit from its batch's
STAMP_TOLERANCE_S = 0.05  # on one clock, a trial's two files cut together start and end this close
SHIFT_FLOOR = 0.5  # a shift is evidence only where its own reference explains at least this much there
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
    swapped_with: str | None = None  # set aside as swapped: the trial whose reference fits it


@dataclass(frozen=True)
class Shift:
    """The trial's own reference searched over a wider window: the best quality inside the usual
    window (`inside`) and outside it (`outside`, at `offset_s`), on the same samples."""

    offset_s: float
    outside: float
    inside: float
    window_s: float  # the usual search window, ±


def is_shift(shift: Shift) -> bool:
    """Whether its own reference fits a trial well, and clearly better, outside the search window."""
    return shift.outside >= SHIFT_FLOOR and clearly_better(shift.outside, shift.inside)


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


Ends = tuple[tuple[float, float], tuple[float, float]]  # (first, last) stamps: estimator, reference


def stamps_shifted(own: Ends, others: list[Ends]) -> str | None:
    """On one clock (`reference.clock: shared`): where the batch's other trials' two files start and
    end together (within STAMP_TOLERANCE_S: cut from one recording at the same times), a reference
    stamped alike late or early at both ends is a shifted clock (the reason). None: no such
    evidence (the batch's files are not cut together, or this one's ends are not displaced alike)."""
    displaced = [(r[0] - f[0], r[1] - f[1]) for f, r in others]
    if len(displaced) < 2 or np.median([max(abs(a), abs(b)) for a, b in displaced]) > STAMP_TOLERANCE_S:
        return None
    (f0, f1), (r0, r1) = own
    start, end = r0 - f0, r1 - f1
    if (
        min(abs(start), abs(end)) <= STAMP_TOLERANCE_S
        or start * end <= 0
        or abs(start - end) > STAMP_TOLERANCE_S
    ):
        return None
    return (
        f"shifted clock: reference.clock: shared, and the batch's other trials' files start and end "
        f"together, but this reference is stamped {start:+.2f} s from the estimator at its start and "
        f"{end:+.2f} s at its end; fix the stamps"
    )


def lag_off_the_batch(lag: float, there: float, at_zero: float, others: list[float]) -> str | None:
    """On one clock: a reference that fits its trial clearly better (and well) at `lag` than at 0,
    where the batch's other trials fit best at lags within LAG_TOLERANCE_S of each other and `lag`
    lies beyond that from theirs, is a shifted clock (the reason). A sensor's own lag is its batch's:
    the same in every trial. None: no such evidence."""
    if len(others) < 2:
        return None
    centre = float(np.median(others))
    spread = float(np.median(np.abs(np.asarray(others) - centre)))
    if spread > LAG_TOLERANCE_S or abs(lag - centre) <= LAG_TOLERANCE_S + 3 * spread:
        return None
    if there < SHIFT_FLOOR or not clearly_better(there, at_zero):
        return None
    return (
        f"shifted clock: reference.clock: shared, yet its reference fits best {lag:+.2f} s off (quality "
        f"{there:.2f}, against {at_zero:.2f} at 0), where the batch's other trials fit best at "
        f"{centre:+.2f} s; fix the stamps"
    )


def copied(what: str, trial: str, original: str, stamped: str, theirs: float, own: float) -> str:
    """The reason a trial is set aside for a stream that is another trial's (`what`: "reference" or
    "estimator stream"; `stamped`: how its stamps relate to the original's; the qualities each
    trial's own files fit with, -1 where they cannot be aligned)."""
    fits = f"{theirs:.2f}" if theirs >= 0 else "none"
    mine = f"{own:.2f}" if own >= 0 else "none"
    return (
        f"the {what} of {trial} is {original}'s: the same values, {stamped} (a file copied for another "
        f"trial? {original}'s own files fit {fits}, this trial's {mine}); set aside whatever "
        "resample.max_offset_s is"
    )


def swapped(partner: str, theirs: float, own: float) -> str:
    """The reason a trial is set aside for another trial's reference."""
    return (
        f"the reference of trial {partner} explains its estimator stream better ({theirs:.2f}) than its "
        f"own ({own:.2f}): reference files swapped?"
    )


def mutual_swaps(
    verdicts: Mapping[str, Verdict], peers: Mapping[str, Mapping[str, float]], own: Mapping[str, float]
) -> list[tuple[str, str]]:
    """(trial, partner) for each trial kept whose partner was set aside as swapped with it, when the
    partner's reference also fits it better (by MARGIN) than its own: a swap seen from both sides
    needs no SWAP_RATIO (the ratio guards against one chance match, not two that agree)."""
    out = []
    for partner, verdict in sorted(verdicts.items()):
        named = verdict.swapped_with
        if named is None or named not in verdicts or verdicts[named].reason is not None:
            continue
        theirs = peers.get(named, {}).get(partner)
        if theirs is not None and theirs >= own[named] + MARGIN:
            out.append((named, partner))
    return out


def shifted(shift: Shift, *, shared: bool) -> str:
    """The reason a trial is set aside for a clock shifted beyond the search window."""
    # On one clock no offset is searched: a wider window would only stop calling the shift one and
    # keep the trial at 0 s, its forces paired with the wrong readings. Only the stamps can be fixed.
    claim, advice = (
        ("reference.clock: shared says 0 s", "fix the stamps")
        if shared
        else (f"the search covers ±{shift.window_s:g} s", "fix the stamps or widen resample.max_offset_s")
    )
    return (
        f"shifted clock: its own reference fits best at an offset of {shift.offset_s:+.2f} s (quality "
        f"{shift.outside:.2f}, against {shift.inside:.2f} within ±{shift.window_s:g} s), but {claim}; "
        f"{advice}"
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
    moved = shift is not None and is_shift(shift)
    # the better of the two explanations wins: another file, or its own file at another offset
    if best_id is not None and clearly_better(best, own) and not (moved and shift.outside > best):
        return Verdict(swapped(best_id, best, own), best, swapped_with=best_id)
    if shift is not None and moved and shift.outside > best:
        return Verdict(shifted(shift, shared=shared), best if best_id is not None else None)
    compared = (
        f"no other trial's reference fits it clearly better (best of {len(peers)}: {best:.2f})"
        if best_id is not None
        else "no other trial in its batch to compare with"
    )
    return Verdict(
        None,
        best if best_id is not None else None,
        f"alignment quality {own:.2f} below resample.min_quality = {min_quality:g}; kept: {compared}, "
        "nor its own reference at another offset",
    )
