"""Resampled batches written as the resample stage writes them, for the split tests."""

from __future__ import annotations

import json
import zlib
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from needlecue_runtime.vocab import AXES
from pipeline.dataset.tables import table_schema, write_table
from pipeline.rig.repeats import samples_sha256

CHANNELS = ["fsr1", "fsr2", "fsr3"]


def write_resampled(
    root: Path,
    batch_id: str,
    trials: dict[str, float],
    channels: list[str] = CHANNELS,
    rate_hz: float = 30.0,
    unit_id: str = "u1",
    purpose: str = "training",
    axes: tuple[str, ...] = AXES,
) -> None:
    """A resampled batch (parquet + json) as the resample stage writes it; trial_id -> angle; its
    reference recorded the force `axes`."""
    cols: dict[str, list] = {name: [] for name in table_schema(channels, axes).names}
    for tid, angle in trials.items():
        rng = np.random.default_rng(zlib.crc32(f"{batch_id}/{tid}".encode()))
        n = int(rng.integers(20, 40))
        cols["batch_id"] += [batch_id] * n
        cols["unit_id"] += [unit_id] * n
        cols["trial_id"] += [tid] * n
        cols["angle_deg"] += [angle] * n
        cols["tissue_point"] += ["p1"] * n
        cols["t_s"] += list(np.arange(n) / rate_hz)
        cols["phase"] += ["rest"] * n
        for c in [*channels, *AXES]:  # every axis drawn, so that the values do not depend on `axes`
            values = list(rng.normal(size=n))
            if c in cols:
                cols[c] += values
    schema = table_schema(channels, axes)
    write_table(
        pa.table({f.name: pa.array(cols[f.name], f.type) for f in schema}, schema=schema),
        root / f"{batch_id}.parquet",
    )
    frame = pd.DataFrame(cols)  # ingest's hash of each trial's samples, as if these were its values
    streams = [(frame[["trial_id", "t_s", *channels]], "t_s"), (frame[["trial_id", "t_s", *axes]], "t_s")]
    meta = {
        "samples_sha256": {tid: samples_sha256(streams, tid) for tid in trials},
        "batch_id": batch_id,
        "channels": channels,
        "rate_hz": rate_hz,
        "unit_id": unit_id,
        "purpose": purpose,
    }
    (root / f"{batch_id}.json").write_text(json.dumps(meta, indent=2, sort_keys=True) + "\n")


def make_input(root: Path, extra_45: int = 0) -> Path:
    """Two training casts at 30 and 45 deg, one held-out batch per angle."""
    root.mkdir(parents=True, exist_ok=True)
    for b in (1, 2):
        trials = {f"a30-t{k:02d}": 30.0 for k in range(1, 9)}
        trials |= {f"a45-t{k:02d}": 45.0 for k in range(1, 9 + (extra_45 if b == 2 else 0))}
        write_resampled(root, f"sim-tissue-{b}", trials)
    write_resampled(root, "sim-heldout-30deg", {f"a30-t{k:02d}": 30.0 for k in range(1, 5)})
    write_resampled(root, "sim-heldout-45deg", {f"a45-t{k:02d}": 45.0 for k in range(1, 5)})
    return root


def trials_in(path: Path) -> set[tuple[str, str]]:
    t = pq.read_table(path, columns=["batch_id", "trial_id"]).to_pydict()
    return set(zip(t["batch_id"], t["trial_id"], strict=True))


def files_of(out: Path) -> dict[str, bytes]:
    return {str(p.relative_to(out)): p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()}
