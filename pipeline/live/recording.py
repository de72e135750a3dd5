"""A live session recorded as a rig-log-style folder (docs/live.md, "The session recording").

    <session>/batch.yaml      rig-log/1 metadata, `purpose: live` (so ingest never trains on it:
                              there is no reference force), the unit's sensor settings, the model
    <session>/lines.csv       everything that came off the port, in order: host time, kind, the raw
                              line (escaped); connects and disconnects too. `needlecue replay` plays it
    <session>/trials.csv      one row per insertion found in the signal, with its cue sequence
    <session>/<trial>.fsr.csv that insertion's samples (host t_ms, counts; board_ms kept beside)
    <session>/<trial>.cues.csv what the trainee was shown, frame by frame: t_s, cue, angle_est_deg,
                              the predicted force of each of the model's targets (fx, fy, fz, or
                              fz alone for a model of a load cell's fz), reason
    <session>/session.json    the session's totals (samples, garbage, gaps, late samples, disconnects)

Every file is written line by line and flushed, so a crash or a pulled plug keeps what arrived.
"""

from __future__ import annotations

import codecs
import contextlib
import csv
import json
from collections.abc import Iterator, Mapping, Sequence
from datetime import date
from pathlib import Path
from typing import IO, Any

import yaml

LINES = "lines.csv"
TRIALS = "trials.csv"
SUMMARY = "session.json"
PURPOSE = "live"
TRIAL_COLUMNS = ["trial_id", "angle_deg", "tissue_point", "start_s", "end_s", "ended", "cues", "final_cue"]


def escape(raw: bytes) -> str:
    """A raw line as printable ASCII (backslash escapes), reversible with `unescape`."""
    return raw.decode("latin-1").encode("unicode_escape").decode("ascii")


def unescape(text: str) -> bytes:
    return codecs.decode(text, "unicode_escape").encode("latin-1")


MAX_RECORDED = 1024  # bytes of one line kept in lines.csv: a longer run of junk is cut (it is garbage anyway)


class _Csv:
    """A CSV file written a row at a time, flushed after each."""

    def __init__(self, path: Path, header: Sequence[str]) -> None:
        self._file: IO[str] = path.open("w", newline="", encoding="utf-8")
        self._writer = csv.writer(self._file)
        self.row(header)

    def row(self, values: Sequence[Any]) -> None:
        self._writer.writerow(values)
        self._file.flush()

    def close(self) -> None:
        self._file.close()


class SessionRecorder:
    """Writes one session's folder as it happens."""

    def __init__(
        self, folder: Path, meta: Mapping[str, Any], channels: Sequence[str], *, targets: Sequence[str]
    ) -> None:
        """`channels`: the unit's, in the order its counts come; `targets`: the force axes the model
        gives (`ForceClient.targets`), one cues.csv column each."""
        if folder.exists() and any(folder.iterdir()):
            raise FileExistsError(f"{folder} exists and is not empty: a recording never overwrites one")
        folder.mkdir(parents=True, exist_ok=True)
        self.folder = folder
        self.failed: str | None = None  # why writing stopped (a full disk, a pulled USB stick), if it did
        self.channels = list(channels)
        self.targets = list(targets)
        self._meta = dict(meta)
        self._write_batch_yaml()
        self._lines = _Csv(folder / LINES, ["host_s", "kind", "text"])
        self._trials = _Csv(folder / TRIALS, TRIAL_COLUMNS)
        self._fsr: _Csv | None = None
        self._cues: _Csv | None = None
        self._last_ms = -1.0

    def _write_batch_yaml(self) -> None:
        doc = {
            "format": "rig-log/1",
            "batch_id": self.folder.name,
            "purpose": PURPOSE,
            "recorded": date.today().isoformat(),
            **self._meta,
        }
        tmp = self.folder / "batch.yaml.tmp"  # written whole, then moved: never a half-written batch.yaml
        tmp.write_text(yaml.safe_dump(doc, sort_keys=False), encoding="utf-8")
        tmp.replace(self.folder / "batch.yaml")

    def _safely(self, write: Any, *args: Any) -> None:
        """Do one write; on an OSError stop recording and say why (`failed`), instead of stopping live."""
        if self.failed is not None:
            return
        try:
            write(*args)
        except OSError as e:
            self.failed = f"{e.strerror or e} ({self.folder})"

    def update_sensor(self, **fields: Any) -> None:
        """The banner told more about the unit than was known at the start: batch.yaml says it."""
        self._meta["sensor"] = {**self._meta.get("sensor", {}), **fields}
        self._safely(self._write_batch_yaml)

    def line(self, host_s: float, kind: str, text: str) -> None:
        self._safely(self._lines.row, [f"{host_s:.6f}", kind, text[:MAX_RECORDED]])

    def begin_trial(self, trial_id: str) -> None:
        self.end_trial_files()
        self._safely(self._open_trial, trial_id)

    def _open_trial(self, trial_id: str) -> None:
        self._fsr = _Csv(self.folder / f"{trial_id}.fsr.csv", ["t_ms", *self.channels, "board_ms"])
        self._cues = _Csv(
            self.folder / f"{trial_id}.cues.csv", ["t_s", "cue", "angle_est_deg", *self.targets, "reason"]
        )

    def sample(self, host_ms: float, board_ms: float, counts: Sequence[int]) -> None:
        if self._fsr is None:
            return
        t = max(host_ms, self._last_ms + 0.001)  # rig-log/1: t_ms strictly increases
        self._last_ms = t
        self._safely(self._fsr.row, [f"{t:.3f}", *counts, f"{board_ms:.0f}"])

    def cue(self, t_s: float, cue: str, angle: float | None, force: Sequence[float], reason: str) -> None:
        if self._cues is not None:
            est = "" if angle is None else f"{angle:.1f}"
            self._safely(self._cues.row, [f"{t_s:.3f}", cue, est, *(f"{f:.5f}" for f in force), reason])

    def end_trial_files(self) -> None:
        for f in (self._fsr, self._cues):
            if f is not None:
                with contextlib.suppress(OSError):
                    f.close()
        self._fsr = self._cues = None
        self._last_ms = -1.0

    def end_trial(self, row: Mapping[str, Any]) -> None:
        self.end_trial_files()
        self._safely(self._trials.row, [row.get(c, "") for c in TRIAL_COLUMNS])

    def close(self, summary: Mapping[str, Any]) -> None:
        self.end_trial_files()
        for f in (self._lines, self._trials):
            with contextlib.suppress(OSError):
                f.close()
        text = json.dumps(summary, indent=2) + "\n"
        self._safely((self.folder / SUMMARY).write_text, text, "utf-8")


def read_lines(folder: Path) -> Iterator[tuple[float, str, str]]:
    """(host_s, kind, text) of a recorded session's lines.csv, in order."""
    path = folder / LINES
    with path.open(newline="", encoding="utf-8") as f:
        reader = csv.reader(f)
        header = next(reader, None)
        if header != ["host_s", "kind", "text"]:
            raise ValueError(f"{path}: not a needlecue live recording (header {header})")
        lineno = 1
        try:
            for lineno, row in enumerate(reader, start=2):
                if len(row) != 3:
                    raise ValueError(f"{path}:{lineno}: {len(row)} fields, expected host_s, kind, text")
                try:
                    yield float(row[0]), row[1], row[2]
                except ValueError as e:
                    raise ValueError(f"{path}:{lineno} column 'host_s': {e}") from e
        except csv.Error as e:
            raise ValueError(f"{path}:{lineno + 1}: not valid CSV: {e}") from e


def read_trials(folder: Path) -> list[dict[str, str]]:
    with (folder / TRIALS).open(newline="", encoding="utf-8") as f:
        return list(csv.DictReader(f))


def read_meta(folder: Path) -> dict[str, Any]:
    """A recorded session's batch.yaml ({} if it is missing, unreadable or not a mapping)."""
    try:
        meta = yaml.safe_load((folder / "batch.yaml").read_text(encoding="utf-8"))
    except (OSError, yaml.YAMLError, UnicodeDecodeError):
        return {}
    return meta if isinstance(meta, dict) else {}


def is_session(folder: Path) -> bool:
    """Whether `folder` is a live session recording (a batch.yaml of purpose live and a lines.csv)."""
    return (folder / LINES).is_file() and read_meta(folder).get("purpose") == PURPOSE
