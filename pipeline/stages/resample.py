"""`resample` stage: align the two clocks of every ingested trial and put both streams on one grid
(`pipeline.signals.resample`), then write the reports (`pipeline.reporting.resample`).

Input: the ingest stage's accepted batches in IN_DIR. Output: `OUT_DIR/<batch_id>.parquet` +
`.json`, and `REPORT_DIR/{offsets.csv, summary.md, offsets.png, trials.png}`. A trial that
cannot be aligned is set aside with its reason in offsets.csv.

Usage: `python -m pipeline.execution.run resample IN_DIR OUT_DIR REPORT_DIR [--params params.yaml]`.
"""

from __future__ import annotations

import logging
from pathlib import Path

import typer

from pipeline.config import ResampleParams, load_section
from pipeline.logs import setup
from pipeline.reporting.resample import write_reports
from pipeline.signals.resample import run

_log = logging.getLogger("pipeline.stages").info  # not __name__: a stage runs as __main__


def main(in_dir: Path, out_dir: Path, report_dir: Path, params: Path = Path("params.yaml")) -> None:
    """Align the clocks and resample every ingested batch onto the common grid."""
    setup()
    try:
        p = load_section(ResampleParams, "resample", params)
        write_reports(run(in_dir, out_dir, p, log=_log), out_dir, report_dir, p)
    except (OSError, ValueError) as e:  # unreadable input, bad params: one clear line, not a traceback
        _log(f"resample: error: {e}")
        raise typer.Exit(1) from e


if __name__ == "__main__":
    typer.run(main)
