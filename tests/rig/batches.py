"""Helpers of the rig tests: copy and break the hand-made lab-bench-a batch, run ingest quietly."""

from __future__ import annotations

import gzip
import shutil
from pathlib import Path

import numpy as np
import pandas as pd

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


def gzip_file(path: Path) -> Path:
    """Replace `path` with `<path>.gz`, its gzip-compressed copy (as `gzip FILE` does)."""
    out = path.with_name(path.name + ".gz")
    out.write_bytes(gzip.compress(path.read_bytes(), mtime=0))
    path.unlink()
    return out


def to_tdms(
    ref_csv: Path,
    *,
    time: str = "channel",
    group: str = "reference",
    unit: str | None = None,
    properties: dict[str, dict[str, object]] | None = None,
    short: str | None = None,
) -> Path:
    """Replace a `<trial>.ref.csv` with `<trial>.ref.tdms` written by npTDMS: one group of float64
    channels fx, fy, fz (and any others of the CSV); the time as a `t_s` channel (time="channel"), as
    NI's waveform properties on every channel (time="waveform") or not at all (time="none"); `unit` as
    each force channel's unit_string; `properties` adds to a channel's properties (channel name ->
    properties); the channel `short` lacks its last sample."""
    from nptdms import ChannelObject, TdmsWriter

    frame = pd.read_csv(ref_csv)
    t = frame.pop("t_s").to_numpy()
    props: dict[str, dict[str, object]] = {c: {} for c in frame.columns}
    if time == "waveform":
        for c in props:
            props[c].update(wf_increment=float(np.median(np.diff(t))), wf_start_offset=float(t[0]))
    for c in props:
        if unit is not None and c in ("fx", "fy", "fz"):
            props[c]["unit_string"] = unit
        props[c].update((properties or {}).get(c, {}))
    data = {c: frame[c].to_numpy(np.float64)[: -1 if c == short else None] for c in frame}
    channels = [ChannelObject(group, c, data[c], properties=props[c]) for c in frame]
    if time == "channel":
        channels.append(ChannelObject(group, "t_s", t.astype(np.float64), properties={"unit_string": "s"}))
    out = ref_csv.with_name(ref_csv.name.removesuffix(".csv") + ".tdms")
    with TdmsWriter(out) as writer:
        writer.write_segment(channels)
    ref_csv.unlink()
    return out
