"""Resampling ingested trials and batches: per trial, units are converted, the clocks aligned
(`pipeline.signals.clock`), both streams put on one uniform grid at `resample.rate_hz` over their
overlap (`pipeline.signals.filters`) and every grid sample given a phase
(`pipeline.signals.phases`); per batch, the trials are assembled into one table
(`pipeline.dataset.tables`).

Input: the ingest stage's accepted batches, `IN_DIR/<batch_id>/{batch.json, trials.parquet,
fsr.parquet, ref.parquet}` (folders without `trials.parquet` were set aside by ingest and are
skipped). Output: `OUT_DIR/<batch_id>.parquet` (every row carries the batch's `unit_id`; the force
columns are the axes the batch's reference records, batch.yaml `reference.axes`, in AXES order) + `.json`
(channels, rate, unit_id, the batch's `purpose`, its declared `front_end` and each trial's samples
hash from ingest), and one offsets.csv row per trial. A trial that cannot be aligned is set aside
with its reason in that row.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pyarrow as pa

from pipeline.config import ResampleParams
from pipeline.dataset.tables import table_schema, write_table
from pipeline.logs import Log
from pipeline.rig.repeats import SAMPLES_KEY
from pipeline.signals import pairing
from pipeline.signals.clock import OffsetEstimate, estimate_offset
from pipeline.signals.filters import SetAside, gap_mask, median_rate, resample_stream
from pipeline.signals.phases import label_phases, phase_durations
from pipeline.signals.scaling import to_newtons, to_volts
from pipeline.vocab import AXES, PHASES, angle_name

WIDE_STEP_S = 0.02  # offsets tried when a trial's own reference is searched wider (see wider)
TRUTH_COLUMN = "sim_clock_offset_s"  # written by the simulator only; a lab's data has no truth
OFFSET_CSV_COLUMNS = (
    "batch_id",
    "trial_id",
    "angle_deg",
    "offset_s",
    "quality",
    "true_offset_s",
    "error_s",
    "n_fsr",
    "n_ref",
    "n_grid",
    "n_dropped_gap",
    "peer_quality",  # below min_quality only: the best quality another trial's reference gave
    "status",
    "flag",  # kept, but looked at: why (a low alignment quality, pipeline.signals.pairing)
)

logger = logging.getLogger(__name__)


@dataclass
class ResampledTrial:
    """One trial on the common grid (host time base; `t_s` starts at 0)."""

    offset: OffsetEstimate
    t0_host_s: float  # host time of grid point t_s = 0
    t_s: np.ndarray
    volts: np.ndarray  # (n, channels)
    force_n: np.ndarray  # (n, axes): the batch's recorded axes (BatchInfo.axes)
    phase: np.ndarray
    n_dropped_gap: int


@dataclass(frozen=True)
class Streams:
    """One trial's two streams, in s, V and N, each strictly increasing in time."""

    t_fsr_s: np.ndarray
    volts: np.ndarray  # (n, channels)
    t_ref_s: np.ndarray
    force_n: np.ndarray  # (m, axes): the axes the reference records, one to three


# An estimator that moves less than this (about two counts of a 10-bit, 5 V ADC) while the reference
# force spans more than this has not recorded the insertion: stuck, dead or unpowered. Any design
# that can sense a needle moves its volts far more over an insertion.
STILL_V = 0.01
MOVED_N = 0.2


def check_response(streams: Streams, channels: tuple[str, ...] | None = None) -> None:
    """SetAside, with that reason, when the estimator, or one of its channels, did not respond to an
    insertion the reference recorded: before the clock alignment, which would blame the clocks. A
    channel is stuck when it moves less than STILL_V while another moves ten times that."""
    if streams.volts.size == 0 or streams.force_n.size == 0:
        return
    moved = np.ptp(streams.volts, axis=0)
    span_n = float(np.max(np.ptp(streams.force_n, axis=0)))
    if span_n < MOVED_N:
        return
    if float(moved.max()) < STILL_V:
        raise SetAside(
            f"the estimator does not respond: its channels move at most {1000 * moved.max():.1f} mV "
            f"while the reference force spans {span_n:.2f} N (stuck at rest, dead or unpowered?)"
        )
    names = channels or tuple(f"channel {k + 1}" for k in range(len(moved)))
    still = moved < STILL_V
    if still.any() and moved.max() >= 10 * STILL_V:
        stuck = [n for n, s in zip(names, still, strict=True) if s]
        raise SetAside(
            f"{', '.join(stuck)} does not respond: moves at most {1000 * moved[still].max():.1f} mV while "
            f"another channel moves {1000 * moved.max():.0f} mV and the reference force spans "
            f"{span_n:.2f} N (a stuck channel)"
        )


def align(fsr: Streams, ref: Streams, p: ResampleParams, *, shared_clock: bool = False) -> OffsetEstimate:
    """The clock offset between `fsr`'s estimator stream and `ref`'s reference stream (usually one
    trial's; another trial's when checking a pairing). Raises SetAside when they cannot be aligned;
    the quality is judged by the caller."""
    if fsr.t_fsr_s.size < 2 or ref.t_ref_s.size < 2:
        raise SetAside("a stream has fewer than two samples")
    if not (np.all(np.isfinite(fsr.volts)) and np.all(np.isfinite(ref.force_n))):
        raise SetAside("missing (NaN) or infinite values in a stream")
    est = estimate_offset(
        fsr.t_fsr_s,
        fsr.volts,
        ref.t_ref_s,
        ref.force_n,
        p.max_offset_s,
        p.offset_step_s,
        p.lowpass_order,
        shared_clock=shared_clock,
    )
    if est.on_edge:
        shift = wider(Streams(fsr.t_fsr_s, fsr.volts, ref.t_ref_s, ref.force_n), p)
        if shift is not None and pairing.is_shift(shift):
            raise SetAside(pairing.shifted(shift, shared=shared_clock))
        raise SetAside(
            f"clock offset at the edge of the ±{p.max_offset_s:g} s search window "
            f"(quality {est.quality:.2f}): the true offset is probably outside it"
        )
    return est


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


def wider(streams: Streams, p: ResampleParams) -> pairing.Shift | None:
    """A trial's own reference tried at offsets up to `pairing.WIDE_FACTOR` times the search window,
    every `WIDE_STEP_S`, each scored on the samples the two streams share at that offset (at least
    half the estimator's): the best quality inside the window and outside it. None: no offset
    outside the window leaves enough overlap."""
    window = pairing.WIDE_FACTOR * p.max_offset_s
    lags = np.arange(-window, window + WIDE_STEP_S / 2, WIDE_STEP_S)
    scores = np.full(lags.size, np.nan)
    t_fsr = streams.t_fsr_s
    for i, lag in enumerate(lags):
        t_ref = streams.t_ref_s + lag
        if np.mean((t_fsr >= t_ref[0]) & (t_fsr <= t_ref[-1])) < 0.5:
            continue
        try:
            scores[i] = estimate_offset(
                t_fsr,
                streams.volts,
                t_ref,
                streams.force_n,
                0.0,
                p.offset_step_s,
                p.lowpass_order,
                shared_clock=True,
            ).quality
        except SetAside:
            continue
    inner = np.abs(lags) <= p.max_offset_s + 1e-9
    if np.all(np.isnan(scores[~inner])) or np.all(np.isnan(scores[inner])):
        return None
    best = int(np.nanargmax(np.where(inner, np.nan, scores)))
    return pairing.Shift(
        float(lags[best]), float(scores[best]), float(np.nanmax(scores[inner])), p.max_offset_s
    )


def on_grid(streams: Streams, est: OffsetEstimate, p: ResampleParams) -> ResampledTrial:
    """One aligned trial put on the common grid and labelled. Raises SetAside."""
    t_fsr_s, volts, t_ref_s, force_n = streams.t_fsr_s, streams.volts, streams.t_ref_s, streams.force_n
    t_ref_host = t_ref_s + est.offset_s
    lo, hi = max(t_fsr_s[0], t_ref_host[0]), min(t_fsr_s[-1], t_ref_host[-1])
    # The grid is anchored to the estimator's own uniform grid, so that at equal rates its
    # (quantised, noisy) samples are copied, not blurred by interpolation.
    fsr_rate = median_rate(t_fsr_s)
    k0 = math.ceil((lo - t_fsr_s[0]) * fsr_rate - 1e-6)
    t0 = t_fsr_s[0] + k0 / fsr_rate
    n = math.floor((hi - t0) * p.rate_hz + 1e-6) + 1 if hi >= t0 else 0
    if n < 10:
        raise SetAside(f"streams overlap for only {max(hi - lo, 0):.2f} s after clock alignment")
    k = np.arange(n)
    grid = t0 + k / p.rate_hz
    v = resample_stream(t_fsr_s, volts, grid, p.rate_hz, p.lowpass_order)
    f = resample_stream(t_ref_host, force_n, grid, p.rate_hz, p.lowpass_order)
    # Phases on the full grid (uniform spacing is what the smoothing assumes), gaps dropped after.
    phase = label_phases(f, p.rate_hz)
    keep = ~(gap_mask(t_fsr_s, grid, p.max_gap_s) | gap_mask(t_ref_host, grid, p.max_gap_s))
    if keep.sum() < 10:
        raise SetAside("fewer than 10 grid points left outside gaps")
    return ResampledTrial(
        offset=est,
        t0_host_s=float(t0),
        t_s=k[keep] / p.rate_hz,
        volts=v[keep],
        force_n=f[keep],
        phase=phase[keep],
        n_dropped_gap=int((~keep).sum()),
    )


@dataclass(frozen=True)
class BatchInfo:
    """What the stage needs from an ingested batch's batch.json."""

    batch_id: str
    unit_id: str
    purpose: str  # training | calibration (batch.yaml; absent = training)
    channels: tuple[str, ...]
    units: str
    adc_bits: int | None
    vref_v: float | None
    ref_units: str
    shared_clock: bool = False  # batch.yaml reference.clock: shared
    axes: tuple[str, ...] = AXES  # batch.yaml reference.axes: the force axes the reference records
    front_end: dict[str, Any] | None = None  # batch.yaml sensor.front_end, as declared (None: absent)
    samples_sha256: dict[str, str] = field(default_factory=dict)  # trial -> its samples' hash (ingest)

    @classmethod
    def from_json(cls, meta: dict[str, Any]) -> BatchInfo:
        s, r = meta["sensor"], meta["reference"]
        return cls(
            shared_clock=r.get("clock") == "shared",
            front_end=s.get("front_end"),
            batch_id=str(meta["batch_id"]),
            unit_id=str(s["unit_id"]),
            purpose=str(meta.get("purpose") or "training"),
            channels=tuple(str(c) for c in s["channels"]),
            units=str(s["units"]),
            adc_bits=None if s.get("adc_bits") is None else int(s["adc_bits"]),
            vref_v=None if s.get("vref_v") is None else float(s["vref_v"]),
            ref_units=str(r["units"]),
            # absent: all three (ingest writes reference.axes only when it is not the default)
            axes=tuple(a for a in AXES if a in (r.get("axes") or AXES)),
            samples_sha256={str(k): str(v) for k, v in (meta.get(SAMPLES_KEY) or {}).items()},
        )


def ingested_batch_dirs(in_dir: Path) -> list[Path]:
    """Accepted ingested batches: visible sub-folders holding trials.parquet, sorted by name.

    Ingest leaves set-aside batches without trials.parquet and writes through `.staging/`.
    """
    if not in_dir.is_dir():
        return []
    return sorted(
        p
        for p in in_dir.iterdir()
        if p.is_dir() and not p.name.startswith(".") and (p / "trials.parquet").is_file()
    )


def _by_trial(df: pd.DataFrame, time_col: str) -> dict[str, pd.DataFrame]:
    df = df.sort_values(["trial_id", time_col], kind="stable")
    return {str(k): g for k, g in df.groupby("trial_id", sort=True)}


def estimator_only(
    t_fsr_s: np.ndarray, volts: np.ndarray, p: ResampleParams
) -> tuple[np.ndarray, np.ndarray]:
    """An estimator stream alone on the common grid (t_s from 0 at its first sample, gaps dropped):
    what a trial whose reference cannot be aligned still gives to a replay. Raises SetAside."""
    t, v = _clean_time(np.asarray(t_fsr_s, dtype=np.float64), np.asarray(volts, dtype=np.float64))
    if t.size < 2 or not np.all(np.isfinite(v)):
        raise SetAside("the estimator stream has fewer than two samples or missing values")
    n = math.floor((t[-1] - t[0]) * p.rate_hz + 1e-6) + 1
    grid = t[0] + np.arange(n) / p.rate_hz
    keep = ~gap_mask(t, grid, p.max_gap_s)
    return np.arange(n)[keep] / p.rate_hz, resample_stream(t, v, grid, p.rate_hz, p.lowpass_order)[keep]


def _clean_time(t: np.ndarray, *arrays: np.ndarray) -> tuple[np.ndarray, ...]:
    """Drop repeated time stamps (keep the first), so every stream is strictly increasing."""
    keep = np.ones(t.size, dtype=bool)
    keep[1:] = np.diff(t) > 0
    return (t[keep], *(a[keep] for a in arrays))


def _num(x: float | None, fmt: str = ".6f") -> str:
    return "" if x is None or not np.isfinite(x) else format(x, fmt)


def process_batch(batch_dir: Path, p: ResampleParams) -> tuple[BatchInfo, pa.Table, list[dict[str, Any]]]:
    """Resample every trial of one ingested batch; returns its info, table and offsets.csv rows."""
    info = BatchInfo.from_json(json.loads((batch_dir / "batch.json").read_text()))
    trials = pd.read_parquet(batch_dir / "trials.parquet")
    fsr = _by_trial(pd.read_parquet(batch_dir / "fsr.parquet"), "t_ms")
    ref = _by_trial(pd.read_parquet(batch_dir / "ref.parquet"), "t_s")
    schema = table_schema(info.channels, info.axes)
    columns: dict[str, list[np.ndarray]] = {name: [] for name in schema.names}
    rows: list[dict[str, Any]] = []
    trials = trials.assign(trial_id=trials["trial_id"].astype(str)).sort_values("trial_id", kind="stable")
    # First every trial's own alignment, then a low quality judged against the batch's other
    # references (pipeline.signals.pairing), then the grid: rows and table in trial order.
    records = trials.to_dict("records")
    built: dict[str, Streams] = {}
    for trial in records:
        tid = str(trial["trial_id"])
        truth = _truth(trial.get(TRUTH_COLUMN))
        row: dict[str, Any] = {
            "batch_id": info.batch_id,
            "trial_id": tid,
            "angle_deg": angle_name(trial["angle_deg"]),
            "offset_s": "",
            "quality": "",
            "true_offset_s": _num(truth),
            "error_s": "",
            "n_fsr": 0,
            "n_ref": 0,
            "n_grid": 0,
            "n_dropped_gap": 0,
            "peer_quality": "",
            "status": "ok",
            "flag": "",
        }
        rows.append(row)
        try:
            if tid not in fsr or tid not in ref:
                raise SetAside("no estimator or no reference samples for this trial")
            fs, rf = fsr[tid], ref[tid]
            row["n_fsr"], row["n_ref"] = len(fs), len(rf)
            t_fsr, volts = _clean_time(
                fs["t_ms"].to_numpy(np.float64) / 1000.0,
                to_volts(
                    fs[list(info.channels)].to_numpy(np.float64), info.units, info.adc_bits, info.vref_v
                ),
            )
            t_ref, force = _clean_time(
                rf["t_s"].to_numpy(np.float64),
                to_newtons(rf[list(info.axes)].to_numpy(np.float64), info.ref_units),
            )
            streams = Streams(t_fsr, volts, t_ref, force)
            check_response(streams, tuple(info.channels))
            built[tid] = streams
        except SetAside as e:
            row["status"] = f"set aside: {e}"
        except KeyError as e:
            row["status"] = f"set aside: missing column {e}"
    # A stream that is another trial's (its values, whatever its stamps) is named before any clock
    # is judged: a copy re-timed beyond the search window would otherwise pass for a shifted clock.
    aligned: dict[str, OffsetEstimate | SetAside] = {}

    def own(tid: str) -> OffsetEstimate | SetAside:
        if tid not in aligned:
            try:
                aligned[tid] = align(built[tid], built[tid], p, shared_clock=info.shared_clock)
            except SetAside as e:
                aligned[tid] = e
        return aligned[tid]

    copies = _copied_streams(built, own)
    usable: dict[str, tuple[Streams, OffsetEstimate]] = {}
    for trial, row in zip(records, rows, strict=True):
        tid = str(trial["trial_id"])
        if tid not in built:
            continue
        if tid in copies:
            row["status"] = f"set aside: {copies[tid]}"
            continue
        est = own(tid)
        if isinstance(est, SetAside):
            row["status"] = f"set aside: {est}"
        else:
            usable[tid] = built[tid], est
    verdicts = _judge_pairings(
        usable, {str(t["trial_id"]): angle_name(t["angle_deg"]) for t in records}, info, p
    )
    for trial, row in zip(records, rows, strict=True):
        tid = str(trial["trial_id"])
        if tid not in usable:
            continue
        streams, est = usable[tid]
        if (verdict := verdicts.get(tid)) is not None:
            row["peer_quality"] = _num(verdict.best_peer, ".4f")
            row["flag"] = verdict.flag or ""
        try:
            if verdict is not None and verdict.reason is not None:
                raise SetAside(verdict.reason)
            res = on_grid(streams, est, p)
        except SetAside as e:
            row["status"] = f"set aside: {e}"
            continue
        truth = _truth(trial.get(TRUTH_COLUMN))
        row["offset_s"] = _num(res.offset.offset_s)
        row["quality"] = _num(res.offset.quality, ".4f")
        if truth is not None:
            row["error_s"] = _num(res.offset.offset_s - truth)
        row["n_grid"], row["n_dropped_gap"] = res.t_s.size, res.n_dropped_gap
        n = res.t_s.size
        columns["batch_id"].append(np.full(n, info.batch_id, dtype=object))
        columns["unit_id"].append(np.full(n, info.unit_id, dtype=object))
        columns["trial_id"].append(np.full(n, tid, dtype=object))
        columns["angle_deg"].append(np.full(n, float(trial["angle_deg"])))
        columns["tissue_point"].append(np.full(n, str(trial["tissue_point"]), dtype=object))
        columns["t_s"].append(res.t_s)
        columns["phase"].append(res.phase)
        for j, c in enumerate(info.channels):
            columns[c].append(res.volts[:, j])
        for j, c in enumerate(info.axes):
            columns[c].append(res.force_n[:, j])
    arrays = [
        pa.array(np.concatenate(columns[f.name]) if columns[f.name] else [], type=f.type) for f in schema
    ]
    return info, pa.Table.from_arrays(arrays, schema=schema), rows


def _judge_pairings(
    usable: dict[str, tuple[Streams, OffsetEstimate]],
    angles: dict[str, str],
    info: BatchInfo,
    p: ResampleParams,
) -> dict[str, pairing.Verdict]:
    """The batch's verdicts on its trials' pairings (pipeline.signals.pairing), copies already set
    aside (`_copied_streams`): per trial below `min_quality`, its estimator stream aligned with
    the references of up to MAX_PEERS other usable trials and with its own reference over a wider
    window, its stamps against the batch's on one clock, and last a swap seen from both sides."""
    out: dict[str, pairing.Verdict] = {}
    usable_angles = {t: angles[t] for t in usable}
    ends = {t: _ends(streams) for t, (streams, _) in usable.items()}
    lags = _best_lags(usable, p) if info.shared_clock else {}
    peers_of: dict[str, dict[str, float]] = {}
    for tid, (streams, est) in usable.items():
        if est.quality >= p.min_quality or tid in out:
            continue
        peers: dict[str, float] = {}
        for other in pairing.peers_of(tid, usable_angles):
            try:
                peers[other] = align(streams, usable[other][0], p, shared_clock=info.shared_clock).quality
            except SetAside:  # too little overlap or an edge: that reference explains nothing here
                peers[other] = 0.0
        peers_of[tid] = peers
        others = [e for t, e in ends.items() if t != tid] if info.shared_clock else None
        off = None  # on one clock: its own reference fits at a lag none of the batch's other trials do
        if tid in lags:
            other_lags = [lag for t, (lag, _) in lags.items() if t != tid]
            off = pairing.lag_off_the_batch(lags[tid][0], lags[tid][1], est.quality, other_lags)
        if off is not None and lags[tid][1] > max(peers.values(), default=0.0):  # the better explanation
            out[tid] = pairing.Verdict(off, max(peers.values(), default=None))
        else:
            out[tid] = _judged(streams, est, peers, p, info.shared_clock, others)
    for tid, partner in pairing.mutual_swaps(out, peers_of, {t: e.quality for t, (_, e) in usable.items()}):
        theirs = peers_of[tid][partner]
        reason = pairing.swapped(partner, theirs, usable[tid][1].quality)
        out[tid] = pairing.Verdict(reason, max(peers_of[tid].values()), swapped_with=partner)
    return out


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


def _copied_streams(
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


def _truth(value: Any) -> float | None:
    """The simulator's true offset, when the trials table carries one."""
    if value is None:
        return None
    try:
        x = float(value)
    except (TypeError, ValueError):
        return None
    return x if np.isfinite(x) else None


def flag_warnings(rows: list[dict[str, Any]]) -> list[str]:
    """One warning line per trial kept with a flag (its alignment quality below `min_quality` with no
    evidence against its files: far below its batch's, or no batch to compare with), naming the
    trial, its quality against the median of the batch's other kept trials, and the flag."""
    kept = {r["trial_id"]: float(r["quality"]) for r in rows if r["status"] == "ok" and r["quality"] != ""}
    out = []
    for r in rows:
        if r["status"] != "ok" or not r.get("flag"):
            continue
        others = [q for t, q in kept.items() if t != r["trial_id"]]
        batch = (
            f"the median of its batch's other {len(others)} kept trials is {np.median(others):.2f}"
            if others
            else "no other trial of its batch is kept"
        )
        out.append(
            f"resample: warning: {r['batch_id']}/{r['trial_id']} kept with alignment quality "
            f"{float(r['quality']):.2f} ({batch}): {r['flag']}"
        )
    return out


@dataclass
class Resampled:
    """What `run` did: one offsets.csv row per trial and the phase durations of every trial kept."""

    rows: list[dict[str, Any]]
    durations: pd.DataFrame


def run(in_dir: Path, out_dir: Path, p: ResampleParams, *, log: Log = logger.info) -> Resampled:
    """Resample every accepted batch of `in_dir` into `out_dir/<batch_id>.{parquet,json}`."""
    out_dir.mkdir(parents=True, exist_ok=True)
    written: set[str] = set()
    all_rows: list[dict[str, Any]] = []
    durations: list[pd.DataFrame] = []
    for batch_dir in ingested_batch_dirs(in_dir):
        info, table, rows = process_batch(batch_dir, p)
        ok = set(table.column("trial_id").to_pylist())
        write_table(table, out_dir / f"{info.batch_id}.parquet")
        meta = {
            "batch_id": info.batch_id,
            "channels": list(info.channels),
            "rate_hz": p.rate_hz,
            "unit_id": info.unit_id,
            "purpose": info.purpose,
            "front_end": info.front_end,
            # the trials resampled: a trial set aside here is in no split, so in no repeat check
            SAMPLES_KEY: {t: h for t, h in info.samples_sha256.items() if t in ok},
        }
        (out_dir / f"{info.batch_id}.json").write_text(json.dumps(meta, indent=2, sort_keys=True) + "\n")
        written |= {f"{info.batch_id}.parquet", f"{info.batch_id}.json"}
        all_rows += rows
        durations.append(phase_durations(table, p.rate_hz))
        n_ok = sum(r["status"] == "ok" for r in rows)
        errs = [abs(float(r["error_s"])) for r in rows if r["error_s"] != ""]
        err_txt = f", offset error median {np.median(errs) * 1e3:.1f} ms" if errs else ""
        log(
            f"resample: {info.batch_id}: {n_ok}/{len(rows)} trials ok, {table.num_rows} grid samples{err_txt}"
        )
        for line in flag_warnings(rows):
            log(line)
    # Files of batches that are gone would otherwise be picked up by `split`.
    for stale in sorted(out_dir.glob("*")):
        if stale.is_file() and stale.suffix in (".parquet", ".json") and stale.name not in written:
            stale.unlink()
    dur = pd.concat(durations) if durations else pd.DataFrame(columns=list(PHASES), dtype=float)
    return Resampled(all_rows, dur)
