"""`ledger` stage: one record of every trial of every batch (`pipeline.ledger`), rendered as Markdown
(`pipeline.reporting.ledger`).

Input: ingest's `batches.json` and `quarantine.json`, resample's `offsets.csv`, split's
`manifest.json` and the calibrate stage's `CAL_DIR/<unit>.json`. Output: `OUT_DIR/ledger.json`
(`needlecue-ledger/1`) and `OUT_DIR/ledger.md`, which `needlecue retrain` reads.

Usage: `python -m pipeline.execution.run ledger BATCHES QUARANTINE OFFSETS MANIFEST CAL_DIR OUT_DIR
[--params params.yaml]`.
"""

from __future__ import annotations

import csv
import json
import logging
from pathlib import Path
from typing import Any

import typer

from pipeline import ledger
from pipeline.config import TrainParams, load_section
from pipeline.logs import setup
from pipeline.reporting.ledger import markdown

_log = logging.getLogger("pipeline.stages").info  # not __name__: a stage runs as __main__


def _json(path: Path, kind: type) -> Any:
    """A stage's JSON record, checked to be the kind of value it should be."""
    value = json.loads(path.read_text())
    if not isinstance(value, kind):
        raise ValueError(f"{path}: expected a JSON {kind.__name__}, found {type(value).__name__}")
    return value


def main(
    batches: Path,
    quarantine: Path,
    offsets: Path,
    manifest: Path,
    cal_dir: Path,
    out_dir: Path,
    params: Path = Path("params.yaml"),
) -> None:
    """Account for every trial: used in which split of which angle, or set aside where and why."""
    setup("ledger")
    try:
        trained = load_section(TrainParams, "train", params).angles
        with offsets.open(newline="") as f:
            rows = list(csv.DictReader(f))
        docs = [_json(p, dict) for p in sorted(cal_dir.glob("*.json"))]
        entries = ledger.build(
            _json(batches, list), _json(quarantine, list), rows, _json(manifest, dict), docs, trained
        )
    except (OSError, ValueError, KeyError, TypeError) as e:  # a missing or malformed record: one line
        _log(f"error: {type(e).__name__}: {e}")
        raise typer.Exit(1) from e
    doc = ledger.document(entries)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "ledger.json").write_text(json.dumps(doc, indent=2, ensure_ascii=False) + "\n")
    (out_dir / "ledger.md").write_text(markdown(doc))
    c = doc["counts"]
    _log(
        f"{c['trials']} trials: {c['used']} used, {c['set_aside']} set aside "
        f"({', '.join(f'{s} {n}' for s, n in c['set_aside_by_stage'].items())}); {out_dir / 'ledger.md'}"
    )


if __name__ == "__main__":
    typer.run(main)
