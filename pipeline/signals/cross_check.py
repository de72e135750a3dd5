"""A batch's trials checked against each other, in memory: a stream that is another trial's, and a low
alignment quality judged against the batch's other references (`pipeline.signals.pairing`)."""

from __future__ import annotations

import hashlib
from collections.abc import Callable

import numpy as np

from pipeline.config import ResampleParams
from pipeline.signals import pairing
from pipeline.signals.clock import OffsetEstimate, estimate_offset
from pipeline.signals.filters import SetAside
from pipeline.signals.trial import Streams, align, wider


def judge_pairings(
    usable: dict[str, tuple[Streams, OffsetEstimate]],
    angles: dict[str, str],
    shared_clock: bool,
    p: ResampleParams,
) -> dict[str, pairing.Verdict]:
    """The batch's verdicts on its trials' pairings (pipeline.signals.pairing), copies already set
    aside (`copied_streams`): per trial below `min_quality`, its estimator stream aligned with
    the references of up to MAX_PEERS other usable trials and with its own reference over a wider
    window, its stamps against the batch's on one clock (`shared_clock`: batch.yaml reference.clock), and
    last a swap seen from both sides."""
    out: dict[str, pairing.Verdict] = {}
    usable_angles = {t: angles[t] for t in usable}
    ends = {t: _ends(streams) for t, (streams, _) in usable.items()}
    lags = _best_lags(usable, p) if shared_clock else {}
    peers_of: dict[str, dict[str, float]] = {}
    for tid, (streams, est) in usable.items():
        if est.quality >= p.min_quality or tid in out:
            continue
        peers: dict[str, float] = {}
        for other in pairing.peers_of(tid, usable_angles):
            try:
                peers[other] = align(streams, usable[other][0], p, shared_clock=shared_clock).quality
            except SetAside:  # too little overlap or an edge: that reference explains nothing here
                peers[other] = 0.0
        peers_of[tid] = peers
        others = [e for t, e in ends.items() if t != tid] if shared_clock else None
        off = None  # on one clock: its own reference fits at a lag none of the batch's other trials do
        if tid in lags:
            other_lags = [lag for t, (lag, _) in lags.items() if t != tid]
            off = pairing.lag_off_the_batch(lags[tid][0], lags[tid][1], est.quality, other_lags)
        if off is not None and lags[tid][1] > max(peers.values(), default=0.0):  # the better explanation
            out[tid] = pairing.Verdict(off, max(peers.values(), default=None))
        else:
            out[tid] = _judged(streams, est, peers, p, shared_clock, others)
    for tid, partner in pairing.mutual_swaps(out, peers_of, {t: e.quality for t, (_, e) in usable.items()}):
        theirs = peers_of[tid][partner]
        reason = pairing.swapped(partner, theirs, usable[tid][1].quality)
        out[tid] = pairing.Verdict(reason, max(peers_of[tid].values()), swapped_with=partner)
    return out


def _judged(
    streams: Streams,
    est: OffsetEstimate,
    peers: dict[str, float],
    p: ResampleParams,
    shared_clock: bool,
    others: list[tuple[tuple[float, float], tuple[float, float]]] | None = None,
) -> pairing.Verdict:
    """The verdict on a low-quality trial (pipeline.signals.pairing): on one clock, its stamps against
    the batch's other trials' (`others`, their (estimator, reference) first and last stamps); then
    the peers' references and its own reference searched wider."""
    if shared_clock and others:
        reason = pairing.stamps_shifted(_ends(streams), others)
        if reason is not None:
            return pairing.Verdict(reason, max(peers.values(), default=None))
    return pairing.judge(est.quality, peers, p.min_quality, wider(streams, p), shared=shared_clock)


def _best_lags(
    usable: dict[str, tuple[Streams, OffsetEstimate]], p: ResampleParams
) -> dict[str, tuple[float, float]]:
    """On one clock: each trial's (lag, quality) where its reference fits best within the window, as if
    the clocks were separate (a sensor's own lag is the batch's; one trial's apart is its stamps')."""
    out = {}
    for tid, (s, _) in usable.items():
        try:
            est = estimate_offset(
                s.t_fsr_s, s.volts, s.t_ref_s, s.force_n, p.max_offset_s, p.offset_step_s, p.lowpass_order
            )
        except SetAside:
            continue
        out[tid] = (est.offset_s, est.quality)
    return out


def _ends(streams: Streams) -> tuple[tuple[float, float], tuple[float, float]]:
    """(first, last) stamp of the estimator stream and of the reference."""
    fsr, ref = streams.t_fsr_s, streams.t_ref_s
    return (float(fsr[0]), float(fsr[-1])), (float(ref[0]), float(ref[-1]))


def copied_streams(
    built: dict[str, Streams], own: Callable[[str], OffsetEstimate | SetAside]
) -> dict[str, str]:
    """{trial: why} for the trials one of whose streams is another trial's (the same values in order,
    whatever their stamps: the same, shifted or re-timed) while the other stream differs. Of the
    trials sharing a stream, the one its own files fit best (`own`: its alignment, or why it has
    none) keeps it; every other is set aside naming it, whatever `resample.max_offset_s` is. (Both
    streams another's is a copied trial: the split stage names it, `pipeline.rig.repeats`.)"""
    out: dict[str, str] = {}
    digests = {t: (_digest(s.volts), _digest(s.force_n)) for t, s in built.items()}
    for which, what in enumerate(("estimator stream", "reference")):
        groups: dict[str, list[str]] = {}
        for tid, both in digests.items():
            groups.setdefault(both[which], []).append(tid)
        for group in groups.values():
            if len(group) < 2 or len({digests[t] for t in group}) < 2:
                continue
            best = max(group, key=lambda t: (_quality(own(t)), t))
            for tid in group:
                if tid != best and tid not in out:
                    out[tid] = pairing.copied(
                        what,
                        tid,
                        best,
                        _stamped(built[tid], built[best], which),
                        _quality(own(best)),
                        _quality(own(tid)),
                    )
    return out


def _quality(est: OffsetEstimate | SetAside) -> float:
    """A trial's alignment quality on its own files; -1 where they cannot be aligned."""
    return est.quality if isinstance(est, OffsetEstimate) else -1.0


def _stamped(copy: Streams, original: Streams, which: int) -> str:
    """How the copied stream's stamps relate to the original's: the same, shifted, or other."""
    a, b = (copy.t_fsr_s, original.t_fsr_s) if which == 0 else (copy.t_ref_s, original.t_ref_s)
    if a.size != b.size:
        return "stamped otherwise"
    shift = a - b
    if np.all(shift == 0):
        return "with the same stamps"
    if float(np.ptp(shift)) <= 1e-6 * max(1.0, float(np.max(np.abs(b)))):
        return f"stamped {float(np.median(shift)):+.2f} s from it"
    return "stamped otherwise"


def _digest(values: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(values).tobytes()).hexdigest()
