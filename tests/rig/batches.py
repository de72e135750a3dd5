"""Helpers of the rig tests: copy and break the hand-made lab-bench-a batch, run ingest quietly."""

from __future__ import annotations

import shutil
from pathlib import Path

from pipeline.config import IngestParams
from pipeline.rig import ingest

A = "lab-bench-a"
TRIALS = ["t001", "t002", "t003"]
CHANNELS = ["left", "right", "top", "bottom"]


def run(roots: list[Path], out: Path, params: IngestParams | None = None) -> ingest.IngestResult:
    return ingest.ingest_batches(roots, out, params or IngestParams(), log=lambda _: None)


def copy_batch(src: Path, root: Path, name: str) -> Path:
    """A copy of batch `src` under `root`, renamed (batch_id follows the folder name)."""
    dst = root / name
    shutil.copytree(src, dst)
    meta = dst / "batch.yaml"
    meta.write_text(meta.read_text().replace(f"batch_id: {src.name}", f"batch_id: {name}"))
    return dst


def lines_of(path: Path) -> list[str]:
    return path.read_text().splitlines()


def write_lines(path: Path, lines: list[str]) -> None:
    path.write_text("\n".join(lines) + "\n")


def set_cell(path: Path, line: int, column: str, value: str) -> None:
    """Replace one CSV cell (line 1 = header)."""
    rows = lines_of(path)
    col = rows[0].split(",").index(column)
    fields = rows[line - 1].split(",")
    fields[col] = value
    rows[line - 1] = ",".join(fields)
    write_lines(path, rows)


def cell(path: Path, line: int, column: str) -> str:
    rows = lines_of(path)
    return rows[line - 1].split(",")[rows[0].split(",").index(column)]


def drop_column(path: Path, column: str) -> None:
    rows = [r.split(",") for r in lines_of(path)]
    col = rows[0].index(column)
    write_lines(path, [",".join(f for i, f in enumerate(r) if i != col) for r in rows])


def replace_in(path: Path, old: str, new: str) -> None:
    text = path.read_text()
    assert old in text
    path.write_text(text.replace(old, new, 1))


def to_counts(b: Path) -> None:
    """Turn the volts batch into a 10-bit counts batch (values rounded to integer counts)."""
    replace_in(b / "batch.yaml", "units: volts", "units: counts\n  adc_bits: 10\n  vref_v: 5.0")
    for f in sorted(b.glob("*.fsr.csv")):
        rows = [r.split(",") for r in lines_of(f)]
        write_lines(
            f,
            [",".join(rows[0])]
            + [",".join([r[0], *(str(round(float(v) / 5.0 * 1023)) for v in r[1:])]) for r in rows[1:]],
        )
