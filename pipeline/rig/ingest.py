"""Ingesting rig-log/1 batch folders into a per-batch Parquet cache (`docs/rig-log-format.md`).

`ingest_batches` reads every batch folder under the input roots (a later root's folder with an
already seen name is set aside), parses each with `pipeline.rig.reader.parse_batch` and writes,
in OUT_DIR/<batch_id>/ (values in raw units: counts or volts, N or mN; no conversion):

- ``batch.json``      batch.yaml as validated (unknown keys kept) plus ``source_dir`` and
  ``samples_sha256``: each accepted trial's samples hash (`pipeline.rig.repeats`)
- ``trials.parquet``  accepted trials: trial_id, angle_deg (float64), tissue_point, extra columns (str)
- ``fsr.parquet``     trial_id, t_ms, one float64 column per ``sensor.channels`` entry, in that order
- ``ref.parquet``     trial_id, t_s, the axes of ``reference.axes`` (fx, fy, fz by default; in that
  order) (+ tx, ty, tz when every accepted trial has them)
- ``problems.json``   this batch's Problems
- ``gx_results.json`` GX validation results per frame kind (scrubbed of run times and ids)
- ``fingerprint.json`` written last: hash of the batch folder's bytes, ingest params, code and
  library versions, plus the outcome (status, trial ids, warnings) used when it is reused.

A batch set aside as a whole still gets a folder, without the Parquet files and batch.json,
so that an unchanged bad batch is not parsed again either. **Downstream stages must skip
folders without trials.parquet** (this also skips ``.staging/``, where batches are written
before being renamed into place). Rows are sorted by trial_id, then by time; no timestamps
are stored, so the same input gives the same bytes. Nothing under the input folders is ever
written, moved or deleted.

Incremental: a batch whose fingerprint (`pipeline.rig.fingerprint`) matches its stored
fingerprint.json is not parsed again (its bytes are hashed, nothing more); folders of batches no
longer present are removed. One batch's folder is written or reused by `pipeline.rig.batch_store`;
`pipeline.rig.check` parses and validates like ingest but writes nothing (`needlecue check`).
"""

from __future__ import annotations

import json
import logging
import shutil
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from needlecue_runtime.vocab import one_line
from pipeline.config import IngestParams
from pipeline.execution.workers import ordered_imap, workers_for
from pipeline.logs import Log
from pipeline.rig.batch_store import FINGERPRINT, STAGING, BatchOutcome, reuse, write_batch
from pipeline.rig.expectations import Validator
from pipeline.rig.fingerprint import fingerprint
from pipeline.rig.format import BATCH_FILE, Problem, batch_dirs
from pipeline.rig.reader import ParsedBatch, parse_batch

WORTH_A_WORKER = 8_000_000  # bytes of batches to parse: less parses faster than a worker loads GX

logger = logging.getLogger(__name__)


@dataclass
class IngestResult:
    """Outcome of one ingest run, batch by batch, plus the output folders it removed."""

    batches: list[BatchOutcome]
    removed: list[str]

    def _ids(self, pred: Callable[[BatchOutcome], bool]) -> list[str]:
        return [b.batch_id for b in self.batches if pred(b)]

    @property
    def parsed(self) -> list[str]:
        return self._ids(lambda b: b.action == "parsed")

    @property
    def reused(self) -> list[str]:
        return self._ids(lambda b: b.action == "reused")

    @property
    def accepted(self) -> list[str]:
        return self._ids(lambda b: b.accepted)

    @property
    def set_aside(self) -> list[str]:
        return self._ids(lambda b: not b.accepted)

    @property
    def problems(self) -> list[Problem]:
        return [p for b in self.batches for p in b.problems]


def _check_disjoint(out_dir: Path, roots: Sequence[Path]) -> None:
    out = out_dir.resolve()
    for root in roots:
        r = root.resolve()
        if out == r or out.is_relative_to(r) or r.is_relative_to(out):
            raise ValueError(f"output folder {out_dir} overlaps input folder {root}: refusing to write there")


def _find_batches(roots: Sequence[Path]) -> tuple[dict[str, Path], list[BatchOutcome]]:
    """Batch folders by name, first root first; later folders of the same name are set aside."""
    found: dict[str, Path] = {}
    dups: list[BatchOutcome] = []
    for root in roots:
        for d in batch_dirs(root):
            if d.name in found:
                p = Problem(
                    d.name,
                    str(d),
                    f"batch_id {d.name!r} was already read from {found[d.name]}; "
                    "this copy is set aside (batch ids must be unique across input folders)",
                )
                dups.append(BatchOutcome(d.name, d, "duplicate", False, [], [], [p], []))
            else:
                found[d.name] = d
    return found, dups


def _read_from(folder: Path) -> Path | None:
    """The input batch folder a stored batch was read from (None if its fingerprint is unreadable)."""
    try:
        return Path(json.loads((folder / FINGERPRINT).read_text())["source_dir"])
    except (OSError, ValueError, KeyError, TypeError):
        return None


def _refuse_vanished_roots(roots: Sequence[Path], out_dir: Path) -> None:
    """An input folder that is missing or holds no batch while `out_dir` holds batches read from it
    is a share not mounted or a wrong path far more often than a lab deleting all its data: stop,
    changing nothing, rather than empty the store."""
    stored = [e for e in sorted(out_dir.iterdir()) if e.is_dir() and e.name != STAGING]
    for root in roots:
        if batch_dirs(root):
            continue
        mine = [e.name for e in stored if (src := _read_from(e)) is not None and src.parent == root]
        if mine:
            state = "missing" if not root.exists() else "empty"
            shown = ", ".join(mine[:5]) + (f" and {len(mine) - 5} more" if len(mine) > 5 else "")
            raise ValueError(
                f"input folder {root} is {state}, but {out_dir} holds {len(mine)} batch(es) read from it "
                f"({shown}); is a share not mounted? Nothing was changed. To drop those batches on "
                f"purpose, delete their folders from {out_dir}"
            )


def _log_outcome(log: Log, i: int, n: int, b: BatchOutcome, seconds: float | None) -> None:
    how = {
        "parsed": f"parsed in {seconds or 0:.1f} s",
        "reused": "reused (unchanged)",
        "duplicate": "duplicate",
    }
    status = (
        f"{len(b.trials_accepted)} trials accepted, {len(b.trials_set_aside)} set aside"
        if b.accepted
        else "SET ASIDE"
    )
    log(one_line(f"ingest [{i}/{n}] {b.batch_id}: {how[b.action]}, {status} ({b.source_dir})"))
    for p in b.problems:
        log(f"    {p}")
    for w in b.warnings:
        log(one_line(f"    warning: {w}"))


_VALIDATOR: list[Validator] = []  # this process's GX context for the batches it parses


def _start_validator(params: IngestParams) -> None:
    _VALIDATOR[:] = [Validator(params)]  # GX itself loads on the first validation


def _parse_job(job: tuple[Path, Path, IngestParams, dict[str, Any]]) -> tuple[BatchOutcome, float]:
    """Parse, validate and write one batch (a job for `ordered_imap`): its outcome and seconds."""
    out_dir, batch_dir, params, fp = job
    start = time.perf_counter()
    try:
        outcome = write_batch(out_dir, parse_batch(batch_dir, params, _VALIDATOR[0]), fp)
    except (ValueError, TypeError, OverflowError, RecursionError) as e:
        # input nothing caught before writing: this batch is set aside, saying so; the others go on
        why = " ".join(f"cannot be ingested: {type(e).__name__}: {e}".split())
        problem = Problem(batch_dir.name, str(batch_dir / BATCH_FILE), f"{why} (please report it)")
        outcome = write_batch(out_dir, ParsedBatch(batch_dir.name, batch_dir, [problem], []), fp)
    return outcome, time.perf_counter() - start


def ingest_batches(
    roots: Sequence[Path],
    out_dir: Path,
    params: IngestParams,
    *,
    log: Log = logger.info,
    workers: int = 1,
) -> IngestResult:
    """Ingest every batch folder under `roots` into `out_dir`, reusing unchanged batches, parsing the
    others on up to `workers` processes (the same outputs on any number).

    Returns what happened to each batch (`.parsed`, `.reused`, `.accepted`, `.set_aside`, `.problems`).
    """
    _check_disjoint(out_dir, roots)
    out_dir.mkdir(parents=True, exist_ok=True)
    _refuse_vanished_roots(roots, out_dir)
    if (out_dir / STAGING).exists():  # unfinished writes of a crashed run
        shutil.rmtree(out_dir / STAGING)
    found, dups = _find_batches(roots)
    jobs, reused = [], {}
    for name, batch_dir in found.items():
        fp = fingerprint(batch_dir, params)
        if (outcome := reuse(out_dir / name, batch_dir, fp)) is not None:
            reused[name] = outcome
        else:
            jobs.append((out_dir, batch_dir, params, fp))
    size = sum(f.stat().st_size for _, batch_dir, _, _ in jobs for f in batch_dir.rglob("*") if f.is_file())
    workers = workers_for(size, WORTH_A_WORKER, workers)
    parsed = ordered_imap(_parse_job, jobs, workers, _start_validator, (params,))
    outcomes: list[BatchOutcome] = []
    n = len(found) + len(dups)
    for i, name in enumerate(found, 1):
        outcome, seconds = (reused[name], None) if name in reused else next(parsed)
        outcomes.append(outcome)
        _log_outcome(log, i, n, outcome, seconds)
    parsed.close()  # the worker processes, if any, end here
    for j, dup in enumerate(dups, len(found) + 1):
        outcomes.append(dup)
        _log_outcome(log, j, n, dup, None)
    if (out_dir / STAGING).exists():
        shutil.rmtree(out_dir / STAGING)
    removed = []
    for entry in sorted(out_dir.iterdir()):
        if entry.is_dir() and entry.name not in found:
            shutil.rmtree(entry)
            removed.append(entry.name)
            log(f"ingest: removed {entry} (batch no longer present)")
    return IngestResult(outcomes, removed)
