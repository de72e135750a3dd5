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

Incremental: a batch whose fingerprint matches its stored fingerprint.json is not parsed
again (its bytes are hashed, nothing more); folders of batches no longer present are removed.
`check_batches` (and `check_folders`, its problems) parse and validate like ingest but write
nothing (`needlecue check`).
"""

from __future__ import annotations

import hashlib
import json
import logging
import shutil
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path
from typing import Any, Literal

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from pipeline.config import IngestParams
from pipeline.execution.workers import ordered_imap, workers_for
from pipeline.logs import Log
from pipeline.rig.expectations import Validator
from pipeline.rig.format import (
    BATCH_FILE,
    FSR_TIME,
    ID_PATTERN,
    REF_TIME,
    TRIAL_COLUMNS,
    TRIALS_FILE,
    Problem,
    batch_dirs,
)
from pipeline.rig.reader import ParsedBatch, parse_batch
from pipeline.rig.repeats import SAMPLES_KEY, samples_sha256
from pipeline.vocab import one_line

FINGERPRINT = "fingerprint.json"
PROBLEMS = "problems.json"
GX_RESULTS = "gx_results.json"
# Batches are written here first and then renamed into place; never a batch folder itself.
STAGING = ".staging"
WORTH_A_WORKER = 8_000_000  # bytes of batches to parse: less parses faster than a worker loads GX
# Bump when the output layout or meaning changes: every stored batch is then parsed again.
OUTPUT_VERSION = 3  # 2: batch.json carries `purpose`; 3: and `samples_sha256`
# The modules of pipeline/rig/ that decide a batch's outputs, hashed into its fingerprint so a
# code change parses every batch again (datadocs.py only renders the reports: not here).
CODE_FILES = (
    "format.py",
    "problems.py",
    "batch_yaml.py",
    "csvfile.py",
    "expectations.py",
    "reader.py",
    "repeats.py",
    "plausible.py",
    "tdmsfile.py",
    "ingest.py",
)

logger = logging.getLogger(__name__)


# --------------------------------------------------------------------------- fingerprint


def _code_sha256() -> str:
    """SHA-256 of the CODE_FILES, by name and bytes."""
    h = hashlib.sha256()
    here = Path(__file__).parent
    for name in CODE_FILES:
        h.update(f"rig/{name}".encode() + b"\0" + (here / name).read_bytes())
    return h.hexdigest()


def fingerprint(batch_dir: Path, params: IngestParams, source_dir: str | None = None) -> dict[str, Any]:
    """What a batch's outputs depend on: its files' names and bytes, params, code, library versions.

    `source_dir` is the folder's name as the ingest stage gives it (default `str(batch_dir)`), so a
    caller reading the same folder by another path (absolute, say) gets the same fingerprint."""
    h = hashlib.sha256()
    files = sorted(
        (p for p in batch_dir.rglob("*") if p.is_file()), key=lambda p: p.relative_to(batch_dir).as_posix()
    )
    for p in files:
        h.update(p.relative_to(batch_dir).as_posix().encode() + b"\0")
        try:
            with p.open("rb") as f:  # read-only, like every access to the input folders
                for chunk in iter(lambda f=f: f.read(1 << 20), b""):
                    h.update(chunk)
        except OSError as e:  # the parse says so, with the file; the fingerprint keeps the reason
            h.update(f"unreadable: {e.strerror}".encode())
        h.update(b"\0")
    parts: dict[str, Any] = {
        "output_version": OUTPUT_VERSION,
        "source_dir": str(batch_dir) if source_dir is None else source_dir,
        "files_sha256": h.hexdigest(),
        "n_files": len(files),
        "params": params.model_dump(mode="json"),
        "code_sha256": _code_sha256(),
        "id_pattern": ID_PATTERN.pattern,  # lives in pipeline/vocab.py, outside CODE_FILES
        "versions": {m: metadata.version(m) for m in ("great_expectations", "pandas", "pyarrow", "npTDMS")},
    }
    parts["fingerprint"] = hashlib.sha256(json.dumps(parts, sort_keys=True).encode()).hexdigest()
    return parts


def write_json(obj: Any, path: Path) -> None:
    """Indented, key order kept, strict JSON (no NaN): how ingest writes its JSON files."""
    path.write_text(json.dumps(obj, indent=2, ensure_ascii=False, allow_nan=False) + "\n")


def _write_parquet(frame: pd.DataFrame, path: Path, str_cols: Sequence[str]) -> None:
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
        _write_parquet(parsed.trials, tmp / "trials.parquet", ["trial_id", "tissue_point", *extras])
        _write_parquet(parsed.fsr, tmp / "fsr.parquet", ["trial_id"])
        _write_parquet(parsed.ref, tmp / "ref.parquet", ["trial_id"])
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


def _reuse(folder: Path, batch_dir: Path, fp: dict[str, Any]) -> BatchOutcome | None:
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
        if (outcome := _reuse(out_dir / name, batch_dir, fp)) is not None:
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


@dataclass(frozen=True)
class CheckedBatch:
    """What ingest would do with one batch folder: its trials accepted and set aside, and why."""

    batch_id: str
    folder: Path
    trials_accepted: list[str]
    trials_set_aside: list[str]
    problems: list[Problem]
    samples_sha256: dict[str, str] = field(default_factory=dict)  # accepted trial -> `repeats` hash


def trial_hashes(parsed: ParsedBatch) -> dict[str, str]:
    """{accepted trial: its samples' sha256} (`pipeline.rig.repeats`)."""
    if not parsed.accepted or parsed.trials is None or parsed.fsr is None or parsed.ref is None:
        return {}
    streams = [(parsed.fsr, FSR_TIME), (parsed.ref, REF_TIME)]
    return {str(t): samples_sha256(streams, str(t)) for t in parsed.trials["trial_id"]}


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
