"""ingest stage: read rig-log/1 batch folders, validate them, write one Parquet set per batch.

    python -m pipeline.ingest RAW_DIR SIM_DIR OUT_DIR REPORT_DIR [--params params.yaml]

Reads every batch folder under RAW_DIR, plus SIM_DIR when `simulate.enabled` (a missing folder
has no batches). Each file is parsed and checked where it is read (`parse_batch`); then the
batch's frames are validated with Great Expectations (`pipeline.validate`). Anything that is
not rig-log/1 (`shared/rig-log-format.md`) becomes a `Problem` naming file, line and column;
that trial (or the whole batch) is set aside and the rest goes on. Nothing under the input
folders is ever written, moved or deleted: they are only opened for reading.

Output, in OUT_DIR/<batch_id>/ (values in raw units: counts or volts, N or mN; no conversion):

- ``batch.json``      batch.yaml as validated (unknown keys kept) plus ``source_dir``
- ``trials.parquet``  accepted trials: trial_id, angle_deg (float64), tissue_point, extra columns (str)
- ``fsr.parquet``     trial_id, t_ms, one float64 column per ``sensor.channels`` entry, in that order
- ``ref.parquet``     trial_id, t_s, fx, fy, fz (+ tx, ty, tz when every accepted trial has them)
- ``problems.json``   this batch's Problems
- ``gx_results.json`` GX validation results per frame kind (scrubbed of run times and ids)
- ``fingerprint.json`` written last: hash of the batch folder's bytes, ingest params, code and
  library versions, plus the outcome (status, trial ids, warnings) used when it is reused.

A batch set aside as a whole still gets a folder, without the Parquet files and batch.json,
so that an unchanged bad batch is not parsed again either. **Downstream stages must skip
folders without trials.parquet** (this also skips ``.staging/``, where batches are written
before being renamed into place). Rows are sorted by trial_id, then by time; no timestamps
are stored, so the same input gives the same bytes.

Incremental: a batch whose fingerprint matches its stored fingerprint.json is not parsed
again (its bytes are hashed, nothing more); folders of batches no longer present are removed.

Reports, rewritten each run in REPORT_DIR: ``quarantine.json`` (every Problem),
``summary.md``, ``gx/<batch_id>.json`` and GX Data Docs under ``data_docs/index.html``.
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
import shutil
import sys
import time
from collections import Counter, defaultdict
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path
from typing import Any, Literal

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import typer
import yaml
from pydantic import ValidationError

from pipeline import riglog, validate
from pipeline.config import IngestParams, SimulateParams, load_section
from pipeline.riglog import (
    BATCH_FILE,
    FSR_TIME,
    REF_COLUMNS,
    REF_TORQUES,
    TRIAL_COLUMNS,
    TRIALS_FILE,
    BatchMeta,
    Problem,
    batch_dirs,
    fsr_file,
    is_valid_id,
    ref_file,
)

FINGERPRINT = "fingerprint.json"
PROBLEMS = "problems.json"
GX_RESULTS = "gx_results.json"
# Batches are written here first and then renamed into place; never a batch folder itself.
STAGING = ".staging"
# Bump when the output layout or meaning changes: every stored batch is then parsed again.
OUTPUT_VERSION = 1
# Per file and column, report this many problems one by one, then one "... and N more" line.
MAX_PER_COLUMN = 5
# Text that to_numeric turns into NaN without being "text in a number column": a missing value.
NAN_LITERALS = frozenset({"", "nan", "+nan", "-nan"})
# Internal columns of the validated frames; a channel of the same name would be ambiguous.
RESERVED = frozenset({"trial_id", "line", "dt"})
FSR_SUFFIX, REF_SUFFIX = fsr_file(""), ref_file("")

Log = Callable[[str], None]
Warn = Callable[[Path, str], None]


def _stderr(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


# --------------------------------------------------------------------------- problems


class _Problems:
    """The Problems of one batch, in discovery order.

    A cell already blamed (same file, line, column) is not blamed again, so GX does not
    repeat what the parser said more precisely. Per file and column at most MAX_PER_COLUMN
    are listed; the rest are counted into one summary Problem (a column of text would
    otherwise flood the report), but every affected trial is still set aside.
    """

    def __init__(self, batch_id: str) -> None:
        self.batch_id = batch_id
        self.items: list[Problem] = []
        self.bad_trials: set[str] = set()
        self.bad_lines: defaultdict[str, set[int]] = defaultdict(set)
        self._cells: set[tuple[str, int, str | None]] = set()
        self._counts: Counter[tuple[str, str | None]] = Counter()
        self._trial_of: dict[tuple[str, str | None], str | None] = {}

    def add(
        self,
        file: str,
        reason: str,
        *,
        trial_id: str | None = None,
        line: int | None = None,
        column: str | None = None,
    ) -> None:
        if trial_id is not None:
            self.bad_trials.add(trial_id)
        if line is not None:
            if (file, line, column) in self._cells:
                return
            self._cells.add((file, line, column))
            self.bad_lines[file].add(line)
        key = (file, column)
        self._counts[key] += 1
        self._trial_of[key] = trial_id
        if self._counts[key] <= MAX_PER_COLUMN:
            self.items.append(Problem(self.batch_id, file, reason, trial_id, line, column))

    def extend(self, problems: Iterable[Problem]) -> None:
        for p in problems:
            self.add(p.file, p.reason, trial_id=p.trial_id, line=p.line, column=p.column)

    def finish(self) -> list[Problem]:
        out = list(self.items)
        for (file, column), n in self._counts.items():
            if n > MAX_PER_COLUMN:
                out.append(
                    Problem(
                        self.batch_id,
                        file,
                        f"... and {n - MAX_PER_COLUMN} more problems in this file and column (not listed)",
                        self._trial_of[(file, column)],
                        None,
                        column,
                    )
                )
        return out


def _group_warnings(warnings: Sequence[tuple[Path, str]]) -> list[str]:
    """One line per kind of warning, naming its files (a few, then a count): not one per file."""
    by_msg: dict[str, list[Path]] = {}
    for path, msg in warnings:
        by_msg.setdefault(msg, []).append(path)
    lines = []
    for msg, paths in by_msg.items():
        if len(paths) == 1:
            lines.append(f"{paths[0]}: {msg}")
        else:
            names = ", ".join(p.name for p in paths[:3]) + (
                f" and {len(paths) - 3} more" if len(paths) > 3 else ""
            )
            lines.append(f"{paths[0].parent}: {msg}: {names}")
    return lines


# --------------------------------------------------------------------------- batch.yaml


def _yaml_line(node: yaml.Node | None, loc: Sequence[Any]) -> int | None:
    """1-based line of the deepest node of `loc` (a pydantic error location) in a composed YAML tree."""
    if node is None:
        return None
    found = node
    for part in loc:
        nxt = None
        if isinstance(found, yaml.MappingNode):
            nxt = next((v for k, v in found.value if getattr(k, "value", None) == str(part)), None)
        elif isinstance(found, yaml.SequenceNode) and isinstance(part, int) and part < len(found.value):
            nxt = found.value[part]
        if nxt is None:
            break
        found = nxt
    return found.start_mark.line + 1


def _duplicate_key(node: yaml.Node | None) -> tuple[str, int] | None:
    """First key that appears twice in one mapping (safe_load would silently keep the last)."""
    if isinstance(node, yaml.MappingNode):
        seen: set[str] = set()
        for k, v in node.value:
            key = getattr(k, "value", None)
            if isinstance(key, str):
                if key in seen:
                    return key, k.start_mark.line + 1
                seen.add(key)
            if found := _duplicate_key(v):
                return found
    elif isinstance(node, yaml.SequenceNode):
        for v in node.value:
            if found := _duplicate_key(v):
                return found
    return None


def _read_meta(batch_dir: Path, probs: _Problems) -> BatchMeta | None:
    """batch.yaml parsed and validated; None (with Problems) if the batch must be set aside."""
    path = batch_dir / BATCH_FILE
    file = str(path)
    if not path.is_file():
        probs.add(file, f"missing {BATCH_FILE}")
        return None
    try:
        text = path.read_bytes().decode("utf-8-sig")
    except OSError as e:
        probs.add(file, f"cannot read: {e.strerror}")
        return None
    except UnicodeDecodeError as e:
        probs.add(file, "not UTF-8 text", line=path.read_bytes()[: e.start].count(b"\n") + 1)
        return None
    try:
        node = yaml.compose(text, Loader=yaml.SafeLoader)
        if dup := _duplicate_key(node):
            probs.add(file, f"key {dup[0]!r} appears twice in one mapping", line=dup[1])
            return None
        data = yaml.safe_load(text)
    except ValueError as e:  # a well-formed but impossible value, e.g. `recorded: 2026-13-45`
        probs.add(file, f"not valid YAML: {e}")
        return None
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        what = getattr(e, "problem", None) or str(e)
        probs.add(file, f"not valid YAML: {what}", line=None if mark is None else mark.line + 1)
        return None
    if not isinstance(data, dict):
        probs.add(file, "must be a mapping of keys to values (see rig-log/1)", line=1)
        return None
    try:
        meta = BatchMeta.model_validate(data)
    except ValidationError as e:
        for err in e.errors():
            loc = tuple(err["loc"])
            key = ".".join(str(p) for p in loc) or "(top level)"
            got = err.get("input")
            shown = (
                f" (got {got!r})"
                if err["type"] != "missing" and isinstance(got, str | int | float | bool)
                else ""
            )
            probs.add(file, f"key {key}: {err['msg']}{shown}", line=_yaml_line(node, loc))
        return None
    ok = True
    if meta.batch_id != batch_dir.name:
        probs.add(
            file,
            f"key batch_id: {meta.batch_id!r} differs from the folder name {batch_dir.name!r}",
            line=_yaml_line(node, ("batch_id",)),
        )
        ok = False
    elif not is_valid_id(meta.batch_id):
        probs.add(
            file,
            f"key batch_id: {meta.batch_id!r} does not match {riglog.ID_PATTERN.pattern}",
            line=_yaml_line(node, ("batch_id",)),
        )
        ok = False
    if clash := sorted(RESERVED & set(meta.sensor.channels)):
        probs.add(
            file,
            f"key sensor.channels: {', '.join(map(repr, clash))} is reserved for ingest's own "
            "columns; rename the channel",
            line=_yaml_line(node, ("sensor", "channels")),
        )
        ok = False
    return meta if ok else None


# --------------------------------------------------------------------------- CSV reading


@dataclass(frozen=True)
class _Csv:
    header: list[str]
    header_line: int
    rows: list[list[str]]
    lines: list[int]


def _read_csv(path: Path, probs: _Problems, trial_id: str | None) -> _Csv | None:
    """Header and data rows with their 1-based line numbers; None (with a Problem) if unreadable."""
    file = str(path)
    try:
        data = path.read_bytes()
    except OSError as e:
        probs.add(file, f"cannot read: {e.strerror}", trial_id=trial_id)
        return None
    try:
        text = data.decode("utf-8-sig")  # tolerate the BOM spreadsheet programs write
    except UnicodeDecodeError as e:
        probs.add(
            file,
            f"not UTF-8 text (byte 0x{data[e.start]:02x})",
            trial_id=trial_id,
            line=data[: e.start].count(b"\n") + 1,
        )
        return None
    reader = csv.reader(io.StringIO(text, newline=""))
    rows: list[list[str]] = []
    lines: list[int] = []
    try:
        for row in reader:
            if row:  # a blank line carries no sample
                rows.append(row)
                lines.append(reader.line_num)
    except csv.Error as e:
        probs.add(file, f"not valid CSV: {e}", trial_id=trial_id, line=reader.line_num)
        return None
    if not rows:
        probs.add(file, "empty file: no header row", trial_id=trial_id)
        return None
    return _Csv([h.strip() for h in rows[0]], lines[0], rows[1:], lines[1:])


def _column_index(
    table: _Csv, required: Sequence[str], file: str, probs: _Problems, trial_id: str | None
) -> dict[str, int] | None:
    """Position of each header name; None (with Problems) if a name repeats or a required one is missing."""
    counts = Counter(table.header)
    dups = [h for h, n in counts.items() if n > 1]
    for h in dups:
        probs.add(
            file,
            f"column {h!r} appears {counts[h]} times in the header",
            trial_id=trial_id,
            line=table.header_line,
            column=h,
        )
    missing = [c for c in required if c not in counts]
    for i, c in enumerate(missing):
        detail = ""
        if i == 0:  # say once what the header looks like instead
            detail = f" (header is {','.join(table.header)!r})"
            if all(_is_number(h) for h in table.header if h):
                detail += "; the first row holds numbers: is the header row missing?"
        probs.add(file, f"missing column {c!r}{detail}", trial_id=trial_id, line=table.header_line, column=c)
    if dups or missing:
        return None
    return {h: i for i, h in enumerate(table.header)}


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _well_formed(
    table: _Csv,
    file: str,
    probs: _Problems,
    trial_of: Callable[[list[str]], str | None],
) -> tuple[list[list[str]], np.ndarray]:
    """Rows with as many fields as the header (others become Problems) and their line numbers."""
    n = len(table.header)
    rows: list[list[str]] = []
    lines: list[int] = []
    for row, line in zip(table.rows, table.lines, strict=True):
        if len(row) == n:
            rows.append(row)
            lines.append(line)
        else:
            probs.add(
                file, f"row has {len(row)} fields, the header has {n}", trial_id=trial_of(row), line=line
            )
    return rows, np.asarray(lines, dtype=np.int64)


def _numbers(
    values: list[str],
    lines: np.ndarray,
    file: str,
    column: str,
    trial_ids: Sequence[str] | str,
    probs: _Problems,
    integer: bool = False,
) -> np.ndarray:
    """Strings to float64. Text, inf and (for counts) fractions become Problems; empty/NaN stay NaN
    and are reported by the GX no-missing-values check."""
    s = pd.Series(values, dtype=object)
    x = np.asarray(pd.to_numeric(s, errors="coerce"), dtype=np.float64)

    def tid(i: int) -> str:
        return trial_ids if isinstance(trial_ids, str) else trial_ids[i]

    bad = np.isnan(x)
    if bad.any():
        for i in np.flatnonzero(bad):
            raw = values[i].strip()
            if raw.lower() not in NAN_LITERALS:
                probs.add(
                    file,
                    f"text {raw!r} in a number column",
                    trial_id=tid(i),
                    line=int(lines[i]),
                    column=column,
                )
    for i in np.flatnonzero(np.isinf(x)):
        probs.add(
            file,
            f"{values[i].strip()!r} is not a finite number",
            trial_id=tid(i),
            line=int(lines[i]),
            column=column,
        )
    if integer:
        finite = np.isfinite(x)
        for i in np.flatnonzero(finite & (x != np.round(np.where(finite, x, 0)))):
            probs.add(
                file,
                f"count {values[i].strip()!r} is not an integer",
                trial_id=tid(i),
                line=int(lines[i]),
                column=column,
            )
    return x


# --------------------------------------------------------------------------- trials.csv


@dataclass(frozen=True)
class _Trials:
    table: pd.DataFrame  # accepted rows so far, output schema
    listed: set[str]  # every trial_id string in trials.csv, good or bad (files of these are no orphans)
    extras: list[str]
    check: validate.Check | None


def _read_trials(
    batch_dir: Path, batch_id: str, probs: _Problems, validator: validate.Validator, warn: Warn
) -> _Trials | None:
    """trials.csv read, checked row by row and validated with GX; None if the batch must be set aside."""
    path = batch_dir / TRIALS_FILE
    file = str(path)
    if not path.is_file():
        probs.add(file, f"missing {TRIALS_FILE}")
        return None
    table = _read_csv(path, probs, None)
    if table is None:
        return None
    idx = _column_index(table, TRIAL_COLUMNS, file, probs, None)
    if idx is None:
        return None
    i_id = idx["trial_id"]
    listed = {r[i_id].strip() for r in table.rows if len(r) > i_id}
    if not table.rows:
        probs.add(file, "lists no trials", line=table.header_line)
        return None
    rows, lines = _well_formed(table, file, probs, lambda r: r[i_id].strip() if len(r) > i_id else None)
    extras = [h for h in table.header if h not in TRIAL_COLUMNS]
    if "" in extras:
        warn(path, "a column without a name is ignored")
        extras = [h for h in extras if h]
    ids = [r[i_id].strip() for r in rows]
    angle = _numbers([r[idx["angle_deg"]] for r in rows], lines, file, "angle_deg", ids, probs)
    frame = pd.DataFrame(
        {
            "trial_id": pd.Series(ids, dtype=object),
            "angle_deg": angle,
            "tissue_point": pd.Series([r[idx["tissue_point"]].strip() for r in rows], dtype=object),
            "line": lines,
        }
    )
    check = None
    if len(frame):
        check = validator.trials(batch_id, frame, file)
        probs.extend(check.problems)
        if check.batch_failed:
            return None
    bad_lines = probs.bad_lines[file]
    keep = [
        i
        for i, (t, ln) in enumerate(zip(ids, lines, strict=True))
        if ln not in bad_lines and t not in probs.bad_trials
    ]
    out = pd.DataFrame(
        {
            "trial_id": [ids[i] for i in keep],
            "angle_deg": angle[keep],
            "tissue_point": [frame["tissue_point"].iat[i] for i in keep],
            **{c: [rows[i][idx[c]] for i in keep] for c in extras},
        }
    )
    # Sorted here so that every frame built from it is in trial_id order too.
    return _Trials(out.sort_values("trial_id", kind="stable", ignore_index=True), listed, extras, check)


# --------------------------------------------------------------------------- streams


def _read_stream(
    path: Path,
    trial_id: str,
    time_col: str,
    values: Sequence[str],
    optional: Sequence[str],
    integer: bool,
    probs: _Problems,
    warn: Warn,
) -> pd.DataFrame | None:
    """One stream file as trial_id, line, time, values (+ optional columns if all present), float64."""
    file = str(path)
    if not path.is_file():
        probs.add(
            file,
            f"trial {trial_id!r} is listed in {TRIALS_FILE} but {path.name} is missing",
            trial_id=trial_id,
        )
        return None
    table = _read_csv(path, probs, trial_id)
    if table is None:
        return None
    required = [time_col, *values]
    idx = _column_index(table, required, file, probs, trial_id)
    if idx is None:
        return None
    opt = [c for c in optional if c in idx]
    if opt and len(opt) != len(optional):
        warn(path, f"only {', '.join(opt)} of {', '.join(optional)} present; ignored")
        opt = []
    if extra := [h for h in table.header if h not in required and h not in optional]:
        warn(path, f"extra column(s) {', '.join(map(repr, extra))} ignored")
    if not table.rows:
        probs.add(file, "empty stream: a header but no samples", trial_id=trial_id)
        return None
    rows, lines = _well_formed(table, file, probs, lambda _: trial_id)
    if not rows:
        return None
    cols = {
        c: _numbers(
            [r[idx[c]] for r in rows], lines, file, c, trial_id, probs, integer=integer and c != time_col
        )
        for c in [*required, *opt]
    }
    return pd.DataFrame({"trial_id": pd.Series([trial_id] * len(rows), dtype=object), "line": lines, **cols})


def _rate_row(frame: pd.DataFrame, file: str, time_col: str, per_second: float) -> dict[str, Any]:
    t = frame[time_col].to_numpy()
    t = t[np.isfinite(t)]
    span = (t.max() - t.min()) / per_second if len(t) > 1 else 0.0
    # No rate without a positive span; the time checks report why.
    rate = round((len(frame) - 1) / span, 3) if span > 0 else np.nan
    return {
        "trial_id": frame["trial_id"].iat[0],
        "file": file,
        "time_column": time_col,
        "n_samples": len(frame),
        "rate_hz": rate,
    }


# --------------------------------------------------------------------------- one batch


@dataclass
class ParsedBatch:
    """Everything read from one batch folder: accepted frames (if any), Problems, GX results."""

    batch_id: str
    source_dir: Path
    problems: list[Problem]
    warnings: list[str]
    meta: BatchMeta | None = None
    trials: pd.DataFrame | None = None
    fsr: pd.DataFrame | None = None
    ref: pd.DataFrame | None = None
    gx: dict[str, dict[str, Any]] = field(default_factory=dict)
    trials_set_aside: list[str] = field(default_factory=list)

    @property
    def accepted(self) -> bool:
        return self.trials is not None and len(self.trials) > 0


def parse_batch(batch_dir: Path, params: IngestParams, validator: validate.Validator) -> ParsedBatch:
    """Read and validate one batch folder (read-only). Never raises on bad input: see `.problems`."""
    batch_id = batch_dir.name
    probs = _Problems(batch_id)
    warnings: list[tuple[Path, str]] = []
    out = ParsedBatch(batch_id, batch_dir, [], [])

    def warn(path: Path, msg: str) -> None:
        warnings.append((path, msg))

    def done() -> ParsedBatch:
        out.problems = probs.finish()
        out.warnings = _group_warnings(warnings)
        return out

    meta = _read_meta(batch_dir, probs)
    if meta is None:
        return done()
    out.meta = meta
    trials = _read_trials(batch_dir, batch_id, probs, validator, warn)
    if trials is None:
        return done()
    if trials.check is not None:
        out.gx["trials"] = trials.check.result
    _orphans(batch_dir, trials.listed, probs, warn)

    channels = list(meta.sensor.channels)
    counts = meta.sensor.units == "counts"
    adc_max = 2**meta.sensor.adc_bits - 1 if counts and meta.sensor.adc_bits else None
    fsr_frames: list[pd.DataFrame] = []
    ref_frames: list[pd.DataFrame] = []
    summary: list[dict[str, Any]] = []
    for tid in trials.table["trial_id"]:
        f = _read_stream(batch_dir / fsr_file(tid), tid, FSR_TIME, channels, (), counts, probs, warn)
        if f is not None:
            fsr_frames.append(f)
            summary.append(_rate_row(f, fsr_file(tid), FSR_TIME, 1000.0))
        r = _read_stream(
            batch_dir / ref_file(tid),
            tid,
            REF_COLUMNS[0],
            REF_COLUMNS[1:],
            REF_TORQUES,
            False,
            probs,
            warn,
        )
        if r is not None:
            ref_frames.append(r)
            summary.append(_rate_row(r, ref_file(tid), REF_COLUMNS[0], 1.0))

    # Torques go through only if every ref stream of the batch has them (no half-empty columns).
    torques = list(REF_TORQUES) if ref_frames and all(REF_TORQUES[0] in r for r in ref_frames) else []
    if not torques and any(REF_TORQUES[0] in r for r in ref_frames):
        warn(batch_dir, "torques ignored: not every reference stream has them")
    ref_cols = [*REF_COLUMNS, *torques]
    folder = str(batch_dir)
    checks: list[validate.Check] = []
    fsr = ref = pd.DataFrame()
    if fsr_frames:
        fsr = pd.concat(fsr_frames, ignore_index=True)
        fsr["dt"] = validate.frame_dt(fsr, FSR_TIME)
        checks.append(
            validator.stream(
                batch_id,
                "fsr",
                fsr,
                FSR_TIME,
                channels,
                adc_max,
                folder,
                lambda t: str(batch_dir / fsr_file(t)),
            )
        )
    if ref_frames:
        ref = pd.concat([r[["trial_id", "line", *ref_cols]] for r in ref_frames], ignore_index=True)
        ref["dt"] = validate.frame_dt(ref, REF_COLUMNS[0])
        checks.append(
            validator.stream(
                batch_id,
                "ref",
                ref,
                REF_COLUMNS[0],
                ref_cols[1:],
                None,
                folder,
                lambda t: str(batch_dir / ref_file(t)),
            )
        )
    if summary:
        checks.append(
            validator.streams(batch_id, pd.DataFrame(summary), folder, lambda name: str(batch_dir / name))
        )
    for check in checks:
        probs.extend(check.problems)
        out.gx[check.kind] = check.result
    if any(c.batch_failed for c in checks):
        return done()

    accepted = [t for t in trials.table["trial_id"] if t not in probs.bad_trials]
    out.trials_set_aside = sorted(trials.listed - set(accepted))
    if not accepted:
        probs.add(
            str(batch_dir / TRIALS_FILE),
            f"no usable trial: all {len(trials.listed)} listed trials "
            "were set aside, so the batch is set aside",
        )
        return done()
    keep = set(accepted)
    out.trials = trials.table[trials.table["trial_id"].isin(keep)]
    out.fsr = fsr.loc[fsr["trial_id"].isin(keep), ["trial_id", FSR_TIME, *channels]]
    out.ref = ref.loc[ref["trial_id"].isin(keep), ["trial_id", *ref_cols]]
    return done()


def _orphans(batch_dir: Path, listed: set[str], probs: _Problems, warn: Warn) -> None:
    """Stream files without a trial row are reported (and not read); other stray files are warned about."""
    for p in sorted(batch_dir.iterdir()):
        name = p.name
        if name.startswith(".") or name in (BATCH_FILE, TRIALS_FILE):
            continue
        if p.is_dir():
            warn(p, "sub-folder ignored")
            continue
        for suffix in (FSR_SUFFIX, REF_SUFFIX):
            if name.endswith(suffix):
                tid = name[: -len(suffix)]
                if tid not in listed:
                    probs.add(
                        str(p), f"no row for trial {tid!r} in {TRIALS_FILE}: file not ingested", trial_id=tid
                    )
                break
        else:
            warn(p, "not a rig-log/1 file; ignored")


# --------------------------------------------------------------------------- fingerprint


def _code_sha256() -> str:
    h = hashlib.sha256()
    for mod_file in (__file__, validate.__file__, riglog.__file__):
        p = Path(mod_file)
        h.update(p.name.encode() + b"\0" + p.read_bytes())
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
        with p.open("rb") as f:  # read-only, like every access to the input folders
            for chunk in iter(lambda f=f: f.read(1 << 20), b""):
                h.update(chunk)
        h.update(b"\0")
    parts: dict[str, Any] = {
        "output_version": OUTPUT_VERSION,
        "source_dir": str(batch_dir) if source_dir is None else source_dir,
        "files_sha256": h.hexdigest(),
        "n_files": len(files),
        "params": params.model_dump(mode="json"),
        "code_sha256": _code_sha256(),
        "versions": {m: metadata.version(m) for m in ("great_expectations", "pandas", "pyarrow")},
    }
    parts["fingerprint"] = hashlib.sha256(json.dumps(parts, sort_keys=True).encode()).hexdigest()
    return parts


# --------------------------------------------------------------------------- outputs


def _dump_json(obj: Any, path: Path) -> None:
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
        _dump_json(
            {**parsed.meta.model_dump(mode="json"), "source_dir": str(parsed.source_dir)}, tmp / "batch.json"
        )
        extras = [c for c in parsed.trials.columns if c not in TRIAL_COLUMNS]
        _write_parquet(parsed.trials, tmp / "trials.parquet", ["trial_id", "tissue_point", *extras])
        _write_parquet(parsed.fsr, tmp / "fsr.parquet", ["trial_id"])
        _write_parquet(parsed.ref, tmp / "ref.parquet", ["trial_id"])
    _dump_json([p.to_dict() for p in parsed.problems], tmp / PROBLEMS)
    if parsed.gx:
        _dump_json(parsed.gx, tmp / GX_RESULTS)
    outcome = {
        "status": "accepted" if parsed.accepted else "set_aside",
        "trials_accepted": trials_ok,
        "trials_set_aside": parsed.trials_set_aside,
        "warnings": parsed.warnings,
    }
    _dump_json({**fp, "outcome": outcome}, tmp / FINGERPRINT)
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
    log(f"ingest [{i}/{n}] {b.batch_id}: {how[b.action]}, {status} ({b.source_dir})")
    for p in b.problems:
        log(f"    {p}")
    for w in b.warnings:
        log(f"    warning: {w}")


def ingest_batches(
    roots: Sequence[Path],
    out_dir: Path,
    params: IngestParams,
    *,
    log: Log = _stderr,
) -> IngestResult:
    """Ingest every batch folder under `roots` into `out_dir`, reusing unchanged batches.

    Returns what happened to each batch (`.parsed`, `.reused`, `.accepted`, `.set_aside`, `.problems`).
    """
    _check_disjoint(out_dir, roots)
    out_dir.mkdir(parents=True, exist_ok=True)
    if (out_dir / STAGING).exists():  # unfinished writes of a crashed run
        shutil.rmtree(out_dir / STAGING)
    found, dups = _find_batches(roots)
    validator: validate.Validator | None = None  # GX only when something must be parsed
    outcomes: list[BatchOutcome] = []
    n = len(found) + len(dups)
    for i, (name, batch_dir) in enumerate(found.items(), 1):
        fp = fingerprint(batch_dir, params)
        outcome = _reuse(out_dir / name, batch_dir, fp)
        seconds = None
        if outcome is None:
            start = time.perf_counter()
            validator = validator or validate.Validator(params)
            outcome = write_batch(out_dir, parse_batch(batch_dir, params, validator), fp)
            seconds = time.perf_counter() - start
        outcomes.append(outcome)
        _log_outcome(log, i, n, outcome, seconds)
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


def check_folders(dirs: Sequence[Path], params: IngestParams) -> list[Problem]:
    """Parse and validate batch folders like ingest does, writing nothing; return every Problem.

    Each dir is a batch folder (it holds batch.yaml or trials.csv) or a folder of batch folders.
    """
    validator = validate.Validator(params)
    problems: list[Problem] = []
    seen: dict[str, Path] = {}
    for d in dirs:
        if not d.is_dir():
            problems.append(Problem(d.name, str(d), "no such folder"))
            continue
        is_batch = (d / BATCH_FILE).exists() or (d / TRIALS_FILE).exists()
        for b in [d] if is_batch else batch_dirs(d):
            if b.name in seen:
                problems.append(
                    Problem(
                        b.name,
                        str(b),
                        f"batch_id {b.name!r} was already read from {seen[b.name]}; this copy is set aside",
                    )
                )
                continue
            seen[b.name] = b
            problems.extend(parse_batch(b, params, validator).problems)
    return problems


# --------------------------------------------------------------------------- reports


def _summary_md(result: IngestResult) -> str:
    acc = [b for b in result.batches if b.accepted]
    lines = [
        "# Ingest summary",
        "",
        "| | batches | trials |",
        "|---|---:|---:|",
        f"| accepted | {len(acc)} | {sum(len(b.trials_accepted) for b in acc)} |",
        f"| set aside | {len(result.batches) - len(acc)} | "
        f"{sum(len(b.trials_set_aside) for b in result.batches)} |",
        "",
        "## Batches",
        "",
    ]
    for b in result.batches:
        state = (
            f"accepted: {len(b.trials_accepted)} trials, {len(b.trials_set_aside)} set aside"
            if b.accepted
            else "**set aside**"
        )
        lines.append(f"- `{b.batch_id}` ({b.source_dir}, {b.action}): {state}")
    problems = result.problems
    lines += ["", f"## Problems ({len(problems)})", ""]
    lines += [f"- {p}" for p in problems] or ["None."]
    warnings = [w for b in result.batches for w in b.warnings]
    if warnings:
        lines += ["", f"## Warnings ({len(warnings)})", ""] + [f"- {w}" for w in warnings]
    if result.removed:
        lines += ["", "## Removed from the ingest output", ""] + [f"- {r}" for r in result.removed]
    lines += [
        "",
        "Details: `quarantine.json`, `gx/<batch_id>.json`, Data Docs in `data_docs/index.html`.",
        "",
    ]
    return "\n".join(lines)


def write_reports(result: IngestResult, report_dir: Path, *, data_docs: bool = True) -> None:
    """quarantine.json, summary.md, gx/<batch_id>.json and GX Data Docs (all rewritten)."""
    report_dir.mkdir(parents=True, exist_ok=True)
    for sub in ("gx", "data_docs"):
        if (report_dir / sub).exists():
            shutil.rmtree(report_dir / sub)
    quarantine = [
        {
            "batch_id": p.batch_id,
            "trial_id": p.trial_id,
            "file": p.file,
            "line": p.line,
            "column": p.column,
            "reason": p.reason,
        }
        for p in result.problems
    ]
    _dump_json(quarantine, report_dir / "quarantine.json")
    (report_dir / "summary.md").write_text(_summary_md(result))
    gx_dir = report_dir / "gx"
    gx_dir.mkdir()
    results = {b.batch_id: b.gx for b in result.batches if b.gx and b.action != "duplicate"}
    for batch_id, res in results.items():
        _dump_json(res, gx_dir / f"{batch_id}.json")
    if data_docs:
        validate.write_data_docs(results, report_dir / "data_docs")


def main(
    raw_dir: Path, sim_dir: Path, out_dir: Path, report_dir: Path, params: Path = Path("params.yaml")
) -> None:
    """Ingest rig-log/1 batches from RAW_DIR (and SIM_DIR if simulate.enabled) into OUT_DIR."""
    ingest_params = load_section(IngestParams, "ingest", params)
    roots = [raw_dir, sim_dir] if load_section(SimulateParams, "simulate", params).enabled else [raw_dir]
    start = time.perf_counter()
    result = ingest_batches(roots, out_dir, ingest_params)
    write_reports(result, report_dir)
    _stderr(
        f"ingest: {len(result.accepted)} batches accepted, {len(result.set_aside)} set aside "
        f"({len(result.parsed)} parsed, {len(result.reused)} reused), {len(result.problems)} problems, "
        f"{time.perf_counter() - start:.1f} s; see {report_dir / 'summary.md'}"
    )


if __name__ == "__main__":
    typer.run(main)
