"""One rig-log/1 batch from its folder to resampled rows, in memory, as ingest and resample would
make them in the pipeline: what `needlecue calibrate` fits a new unit on and `needlecue replay`
plays. Nothing is written beside the batch; the pipeline's folders are not touched."""

from __future__ import annotations

import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from needlecue_runtime.frontend import is_declared
from pipeline.config import IngestParams, ResampleParams
from pipeline.rig.batch_store import write_batch
from pipeline.rig.expectations import Validator
from pipeline.rig.fingerprint import fingerprint
from pipeline.rig.format import Problem
from pipeline.rig.reader import ParsedBatch, parse_batch
from pipeline.signals import resample, trial
from pipeline.signals.filters import SetAside
from pipeline.signals.scaling import to_volts


@dataclass(frozen=True)
class OneBatch:
    """A batch read and resampled: empty `rows` when nothing could be (the problems and `set_aside`
    say why)."""

    batch_id: str
    unit_id: str | None  # batch.yaml sensor.unit_id (None: the batch could not be read)
    purpose: str | None  # batch.yaml purpose
    problems: list[Problem]
    set_aside: list[str]  # "<batch>/<trial>: why", for every trial not in `rows`
    rows: pd.DataFrame  # the resampled rows, as the resample stage writes them
    front_end: dict[str, Any] | None  # the circuit the batch declares (None: not declared)
    # the estimator streams alone of the trials ingest accepted and resample set aside (their
    # reference could not be aligned): on the same grid, without forces, for a replay
    estimator_only: pd.DataFrame = field(default_factory=pd.DataFrame)


def read_batch(batch_dir: Path, ingest: IngestParams, params: ResampleParams) -> OneBatch:
    """Parse and validate `batch_dir` as ingest does, then resample its accepted trials."""
    parsed = parse_batch(batch_dir, ingest, Validator(ingest))
    if not parsed.accepted or parsed.meta is None:
        return OneBatch(parsed.batch_id, None, None, parsed.problems, [], pd.DataFrame(), None)
    aside = [f"{parsed.batch_id}/{t}: see the problems above" for t in parsed.trials_set_aside]
    with tempfile.TemporaryDirectory(prefix="needlecue-batch-") as tmp:
        work = Path(tmp)
        write_batch(work / "ingested", parsed, fingerprint(batch_dir, ingest))
        resampled = resample.run(work / "ingested", work / "resampled", params, log=lambda _m: None)
        aside += [
            f"{r['batch_id']}/{r['trial_id']}: {r['status']}" for r in resampled.rows if r["status"] != "ok"
        ]
        data = work / "resampled" / f"{parsed.batch_id}.parquet"
        rows = pd.read_parquet(data) if data.is_file() else pd.DataFrame()
    unaligned = [str(r["trial_id"]) for r in resampled.rows if r["status"] != "ok"]
    front_end = parsed.meta.sensor.front_end
    return OneBatch(
        parsed.batch_id,
        parsed.meta.sensor.unit_id,
        parsed.meta.purpose,
        parsed.problems,
        aside,
        rows,
        front_end if is_declared(front_end) else None,
        _estimator_only(parsed, unaligned, params),
    )


def _estimator_only(parsed: ParsedBatch, trial_ids: list[str], params: ResampleParams) -> pd.DataFrame:
    """The estimator streams of `trial_ids` alone on the common grid (trial.estimator_only)."""
    if not trial_ids or parsed.fsr is None or parsed.trials is None or parsed.meta is None:
        return pd.DataFrame()
    sensor = parsed.meta.sensor
    channels = list(sensor.channels)
    angles = dict(zip(parsed.trials["trial_id"].astype(str), parsed.trials["angle_deg"], strict=True))
    frames = []
    for tid in trial_ids:
        fs = parsed.fsr[parsed.fsr["trial_id"].astype(str) == tid].sort_values("t_ms", kind="stable")
        volts = to_volts(fs[channels].to_numpy(np.float64), sensor.units, sensor.adc_bits, sensor.vref_v)
        try:
            t_s, v = trial.estimator_only(fs["t_ms"].to_numpy(np.float64) / 1000.0, volts, params)
        except SetAside:
            continue
        frame = pd.DataFrame({"t_s": t_s, **{c: v[:, j] for j, c in enumerate(channels)}})
        frames.append(
            frame.assign(
                batch_id=parsed.batch_id, unit_id=sensor.unit_id, trial_id=tid, angle_deg=angles[tid]
            )
        )
    return pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()
