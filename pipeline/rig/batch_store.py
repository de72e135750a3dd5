"""One batch's folder in the ingest cache: written into a hidden temp folder, fingerprint last, then
swapped in (`write_batch`), or its stored outcome reused when its fingerprint matches (`reuse`)."""

from __future__ import annotations

import json
import shutil
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from pipeline.rig.format import FSR_TIME, REF_TIME, TRIAL_COLUMNS, Problem
from pipeline.rig.reader import ParsedBatch
from pipeline.rig.repeats import SAMPLES_KEY, samples_sha256

FINGERPRINT = "fingerprint.json"
PROBLEMS = "problems.json"
GX_RESULTS = "gx_results.json"
# Batches are written here first and then renamed into place; never a batch folder itself.
STAGING = ".staging"


def write_json(obj: Any, path: Path) -> None:
    """Indented, key order kept, strict JSON (no NaN): how ingest writes its JSON files."""
    path.write_text(json.dumps(obj, indent=2, ensure_ascii=False, allow_nan=False) + "\n")


def write_parquet(frame: pd.DataFrame, path: Path, str_cols: Sequence[str]) -> None:
    # Explicit Arrow types: no pandas index/metadata, the same bytes for the same values.
    arrays = {
        c: pa.array([str(v) for v in frame[c]], type=pa.string())
        if c in str_cols
        else pa.array(frame[c].to_numpy(dtype=np.float64), type=pa.float64())
        for c in frame.columns
    }
    pq.write_table(pa.table(arrays), path)


@dataclass
class BatchOutcome:
    """What ingest did with one batch folder: parsed now, reused (fingerprint matched) or duplicate."""

    batch_id: str
    source_dir: Path
    action: Literal["parsed", "reused", "duplicate"]
    accepted: bool
    trials_accepted: list[str]
    trials_set_aside: list[str]
    problems: list[Problem]
    warnings: list[str]
    gx: dict[str, dict[str, Any]] = field(default_factory=dict)


def write_batch(out_dir: Path, parsed: ParsedBatch, fp: dict[str, Any]) -> BatchOutcome:
    """Write one batch's outputs into a hidden temp folder, fingerprint last, then swap it in.

    A crash leaves either the old complete folder, or no folder, or a hidden leftover that the
    next run deletes; never a fingerprint next to half-written files.
    """
    name = parsed.batch_id
    staging = out_dir / STAGING
    tmp, old, final = staging / name, staging / f"{name}.old", out_dir / name
    for leftover in (tmp, old):
        if leftover.exists():
            shutil.rmtree(leftover)
    tmp.mkdir(parents=True)
    trials_ok = list(parsed.trials["trial_id"]) if parsed.accepted and parsed.trials is not None else []
    if parsed.accepted:
        assert parsed.meta is not None and parsed.trials is not None
        assert parsed.fsr is not None and parsed.ref is not None
        meta = {**parsed.meta.model_dump(mode="json"), "source_dir": str(parsed.source_dir)}
        write_json({**meta, SAMPLES_KEY: trial_hashes(parsed)}, tmp / "batch.json")
        extras = [c for c in parsed.trials.columns if c not in TRIAL_COLUMNS]
        write_parquet(parsed.trials, tmp / "trials.parquet", ["trial_id", "tissue_point", *extras])
        write_parquet(parsed.fsr, tmp / "fsr.parquet", ["trial_id"])
        write_parquet(parsed.ref, tmp / "ref.parquet", ["trial_id"])
    write_json([p.to_dict() for p in parsed.problems], tmp / PROBLEMS)
    if parsed.gx:
        write_json(parsed.gx, tmp / GX_RESULTS)
    outcome = {
        "status": "accepted" if parsed.accepted else "set_aside",
        "trials_accepted": trials_ok,
        "trials_set_aside": parsed.trials_set_aside,
        "warnings": parsed.warnings,
    }
    write_json({**fp, "outcome": outcome}, tmp / FINGERPRINT)
    if final.exists():
        final.rename(old)
    tmp.rename(final)
    if old.exists():
        shutil.rmtree(old)
    return BatchOutcome(
        name,
        parsed.source_dir,
        "parsed",
        parsed.accepted,
        trials_ok,
        parsed.trials_set_aside,
        parsed.problems,
        parsed.warnings,
        parsed.gx,
    )


def reuse(folder: Path, batch_dir: Path, fp: dict[str, Any]) -> BatchOutcome | None:
    """The stored outcome if folder/fingerprint.json matches `fp` and its outputs are all there."""
    try:
        stored = json.loads((folder / FINGERPRINT).read_text())
        if stored.get("fingerprint") != fp["fingerprint"]:
            return None
        outcome = stored["outcome"]
        accepted = outcome["status"] == "accepted"
        needed = [
            PROBLEMS,
            *(["batch.json", "trials.parquet", "fsr.parquet", "ref.parquet"] if accepted else []),
        ]
        if not all((folder / n).is_file() for n in needed):
            return None
        problems = [Problem(**p) for p in json.loads((folder / PROBLEMS).read_text())]
        gx = json.loads((folder / GX_RESULTS).read_text()) if (folder / GX_RESULTS).is_file() else {}
    except (OSError, ValueError, KeyError, TypeError):
        return None  # unreadable or from an older layout: parse again
    return BatchOutcome(
        folder.name,
        batch_dir,
        "reused",
        accepted,
        outcome["trials_accepted"],
        outcome["trials_set_aside"],
        problems,
        outcome["warnings"],
        gx,
    )


def trial_hashes(parsed: ParsedBatch) -> dict[str, str]:
    """{accepted trial: its samples' sha256} (`pipeline.rig.repeats`)."""
    if not parsed.accepted or parsed.trials is None or parsed.fsr is None or parsed.ref is None:
        return {}
    streams = [(parsed.fsr, FSR_TIME), (parsed.ref, REF_TIME)]
    return {str(t): samples_sha256(streams, str(t)) for t in parsed.trials["trial_id"]}
