"""Batch folders parsed and validated like ingest does, writing nothing (`needlecue check`, and the
retrain command's look at new batches)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from pipeline.config import IngestParams
from pipeline.rig.batch_store import trial_hashes
from pipeline.rig.expectations import Validator
from pipeline.rig.format import BATCH_FILE, TRIALS_FILE, Problem, batch_dirs
from pipeline.rig.reader import parse_batch


@dataclass(frozen=True)
class CheckedBatch:
    """What ingest would do with one batch folder: its trials accepted and set aside, and why."""

    batch_id: str
    folder: Path
    trials_accepted: list[str]
    trials_set_aside: list[str]
    problems: list[Problem]
    samples_sha256: dict[str, str] = field(default_factory=dict)  # accepted trial -> `repeats` hash


def check_batches(dirs: Sequence[Path], params: IngestParams) -> list[CheckedBatch]:
    """Parse and validate batch folders like ingest does, writing nothing.

    Each dir is a batch folder (it holds batch.yaml or trials.csv) or a folder of batch folders.
    """
    validator = Validator(params)
    out: list[CheckedBatch] = []
    seen: dict[str, Path] = {}
    for d in dirs:
        if not d.is_dir():
            out.append(CheckedBatch(d.name, d, [], [], [Problem(d.name, str(d), "no such folder")]))
            continue
        is_batch = (d / BATCH_FILE).exists() or (d / TRIALS_FILE).exists()
        for b in [d] if is_batch else batch_dirs(d):
            if b.name in seen:
                why = f"batch_id {b.name!r} was already read from {seen[b.name]}; this copy is set aside"
                out.append(CheckedBatch(b.name, b, [], [], [Problem(b.name, str(b), why)]))
                continue
            seen[b.name] = b
            parsed = parse_batch(b, params, validator)
            accepted = (
                list(parsed.trials["trial_id"]) if parsed.accepted and parsed.trials is not None else []
            )
            hashes = trial_hashes(parsed)
            out.append(CheckedBatch(b.name, b, accepted, parsed.trials_set_aside, parsed.problems, hashes))
    return out


def check_folders(dirs: Sequence[Path], params: IngestParams) -> list[Problem]:
    """Every Problem `check_batches` finds."""
    return [p for c in check_batches(dirs, params) for p in c.problems]
