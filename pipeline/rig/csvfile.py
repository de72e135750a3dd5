"""Reading the CSV files of a batch cell by cell: every unreadable file, bad header, malformed
row or non-number becomes a `Problem` naming its file, line and column
(`docs/rig-log-format.md`, "Invalid input and what happens to it").
"""

from __future__ import annotations

import csv
import gzip
import io
import zlib
from collections import Counter
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from pipeline.rig.format import GZIP
from pipeline.rig.problems import ProblemLog

# A gzip-compressed CSV is read up to this many bytes: a trial of one insertion is a few MB, and a
# small file that inflates to gigabytes (a "zip bomb") is refused instead of filling the memory: parsed,
# text takes some 30 times its size, so 64 MiB of CSV is about 2 GB at its peak.
MAX_GUNZIPPED_BYTES = 64 * 2**20

# Text that to_numeric turns into NaN without being "text in a number column": a missing value.
NAN_LITERALS = frozenset({"", "nan", "+nan", "-nan"})


def encoding_hint(data: bytes) -> str:
    """What a file that is not UTF-8 seems to be, as a hint to re-save it (rig-log/1 is UTF-8)."""
    if data.startswith((b"\xff\xfe", b"\xfe\xff")) or (len(data) > 1 and b"\x00" in data[:200]):
        return ": it looks like UTF-16; save it as UTF-8"
    try:
        data.decode("cp1252")
    except UnicodeDecodeError:
        return ""
    return ": it looks like Windows-1252 (cp1252); save it as UTF-8"


@dataclass(frozen=True)
class CsvTable:
    """A CSV file's header and non-blank data rows, each with its 1-based line number."""

    header: list[str]
    header_line: int
    rows: list[list[str]]
    lines: list[int]
    cut_short: bool = False  # the file does not end with a line break: the last row may be cut off


def read_csv(path: Path, probs: ProblemLog, trial_id: str | None) -> CsvTable | None:
    """Header and data rows with their 1-based line numbers; None (with a Problem) if unreadable."""
    file = str(path)
    try:
        data = path.read_bytes()
    except OSError as e:
        probs.add(file, f"cannot read: {e.strerror}", trial_id=trial_id)
        return None
    if path.name.endswith(GZIP):
        try:
            with gzip.GzipFile(fileobj=io.BytesIO(data)) as z:
                data = z.read(MAX_GUNZIPPED_BYTES + 1)
        except (OSError, EOFError, zlib.error) as e:  # BadGzipFile is an OSError; EOFError: cut short
            probs.add(file, f"not a readable gzip file: {e or type(e).__name__}", trial_id=trial_id)
            return None
        if len(data) > MAX_GUNZIPPED_BYTES:
            limit = MAX_GUNZIPPED_BYTES // 2**20
            probs.add(file, f"decompresses to more than {limit} MiB: refused", trial_id=trial_id)
            return None
    try:
        text = data.decode("utf-8-sig")  # tolerate the BOM spreadsheet programs write
    except UnicodeDecodeError as e:
        probs.add(
            file,
            f"not UTF-8 text (byte 0x{data[e.start]:02x}){encoding_hint(data)}",
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
    cut = not text.endswith(("\n", "\r"))
    return CsvTable([h.strip() for h in rows[0]], lines[0], rows[1:], lines[1:], cut)


def column_index(
    table: CsvTable,
    required: Sequence[str],
    file: str,
    probs: ProblemLog,
    trial_id: str | None,
    why: Mapping[str, str] | None = None,
) -> dict[str, int] | None:
    """Position of each header name; None (with Problems) if a name repeats or a required one is missing
    (`why` adds to a missing column's reason: what asked for it)."""
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
        reason = f"missing column {c!r}{detail}{(why or {}).get(c, '')}"
        probs.add(file, reason, trial_id=trial_id, line=table.header_line, column=c)
    if dups or missing:
        return None
    return {h: i for i, h in enumerate(table.header)}


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def well_formed(
    table: CsvTable,
    file: str,
    probs: ProblemLog,
    trial_of: Callable[[list[str]], str | None],
    warn: Callable[[str], None] | None = None,
) -> tuple[list[list[str]], np.ndarray]:
    """Rows with as many fields as the header (others become Problems) and their line numbers.
    With `warn`, a last row cut short (fewer fields, no line break after it: a recording that lost
    power) is dropped with a warning instead: the samples before it are whole."""
    n = len(table.header)
    rows: list[list[str]] = []
    lines: list[int] = []
    last = len(table.rows) - 1
    for k, (row, line) in enumerate(zip(table.rows, table.lines, strict=True)):
        if warn is not None and k == last and table.cut_short and len(row) < n:
            warn(f"line {line}: the last row is cut short ({len(row)} of {n} fields, no line break): dropped")
            continue
        if len(row) == n:
            rows.append(row)
            lines.append(line)
        else:
            probs.add(
                file, f"row has {len(row)} fields, the header has {n}", trial_id=trial_of(row), line=line
            )
    return rows, np.asarray(lines, dtype=np.int64)


def numbers(
    values: list[str],
    lines: np.ndarray,
    file: str,
    column: str,
    trial_ids: Sequence[str] | str,
    probs: ProblemLog,
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
