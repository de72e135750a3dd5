"""Resampling ingested batches, from their files to the resampled tables: per trial, units are
converted, then its two streams aligned and put on the common grid (`pipeline.signals.trial`), once
the batch's trials are checked against each other (`pipeline.signals.cross_check`); per batch, the
trials are assembled into one table (`pipeline.dataset.tables`).

Input: the ingest stage's accepted batches, `IN_DIR/<batch_id>/{batch.json, trials.parquet,
fsr.parquet, ref.parquet}` (folders without `trials.parquet` were set aside by ingest and are
skipped). Output: `OUT_DIR/<batch_id>.parquet` (every row carries the batch's `unit_id`; the force
columns are the axes the batch's reference records, batch.yaml `reference.axes`, in AXES order) + `.json`
(channels, rate, unit_id, the batch's `purpose`, its declared `front_end` and each trial's samples
hash from ingest), and one offsets.csv row per trial. A trial that cannot be aligned is set aside
with its reason in that row.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pyarrow as pa

from needlecue_runtime.vocab import AXES, PHASES, angle_name
from pipeline.config import ResampleParams
from pipeline.dataset.tables import table_schema, write_table
from pipeline.logs import Log
from pipeline.rig.repeats import SAMPLES_KEY
from pipeline.signals.clock import OffsetEstimate
from pipeline.signals.cross_check import copied_streams, judge_pairings
from pipeline.signals.filters import SetAside
from pipeline.signals.phases import phase_durations
from pipeline.signals.scaling import to_newtons, to_volts
from pipeline.signals.trial import Streams, align, check_response, clean_time, on_grid

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
            t_fsr, volts = clean_time(
                fs["t_ms"].to_numpy(np.float64) / 1000.0,
                to_volts(
                    fs[list(info.channels)].to_numpy(np.float64), info.units, info.adc_bits, info.vref_v
                ),
            )
            t_ref, force = clean_time(
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

    copies = copied_streams(built, own)
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
    verdicts = judge_pairings(
        usable, {str(t["trial_id"]): angle_name(t["angle_deg"]) for t in records}, info.shared_clock, p
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
