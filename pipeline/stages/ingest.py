"""`ingest` stage: read rig-log/1 batch folders, validate them and keep one Parquet set per batch
(`pipeline.rig.ingest`), then write the reports (`pipeline.reporting.ingest`).

Reads every batch folder under RAW_DIR, plus SIM_DIR when `simulate.enabled` (a missing folder
has no batches). Anything that is not rig-log/1 (`docs/rig-log-format.md`) becomes a Problem
naming file, line and column; that trial (or the whole batch) is set aside and the rest goes on.
Unchanged batches are reused, not parsed again. The input folders are only read.

Usage: `python -m pipeline.execution.run ingest RAW_DIR SIM_DIR OUT_DIR REPORT_DIR [--params params.yaml]`.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import typer

from pipeline.config import IngestParams, SimulateParams, load_section
from pipeline.execution.workers import WORKERS
from pipeline.logs import setup
from pipeline.reporting.ingest import write_reports
from pipeline.rig.ingest import ingest_batches

_log = logging.getLogger("pipeline.stages").info  # not __name__: a stage runs as __main__


def main(
    raw_dir: Path, sim_dir: Path, out_dir: Path, report_dir: Path, params: Path = Path("params.yaml")
) -> None:
    """Ingest rig-log/1 batches from RAW_DIR (and SIM_DIR if simulate.enabled) into OUT_DIR."""
    setup()
    start = time.perf_counter()
    try:
        ingest_params = load_section(IngestParams, "ingest", params)
        simulated = load_section(SimulateParams, "simulate", params).enabled
        roots = [raw_dir, sim_dir] if simulated else [raw_dir]
        result = ingest_batches(roots, out_dir, ingest_params, log=_log, workers=WORKERS)
        write_reports(result, report_dir)
    except (OSError, ValueError) as e:  # overlapping folders, bad params: one clear line, not a traceback
        _log(f"ingest: error: {e}")
        raise typer.Exit(1) from e
    _log(
        f"ingest: {len(result.accepted)} batches accepted, {len(result.set_aside)} set aside "
        f"({len(result.parsed)} parsed, {len(result.reused)} reused), {len(result.problems)} problems, "
        f"{time.perf_counter() - start:.1f} s; see {report_dir / 'summary.md'}"
    )


if __name__ == "__main__":
    typer.run(main)
