"""One batch folder read for `needlecue calibrate` and `replay`: its problems printed, and the
command ended when nothing in it is usable."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import typer

from pipeline.cli.params import section
from pipeline.exits import fail


def checked_batch(
    batch_dir: Path,
    unit_id: str | None,
    params: Path,
    purpose: str | None = None,
    *,
    need_reference: bool = True,
) -> Any:
    """`read_batch` with its problems printed. typer.Exit(1) if nothing is usable (with
    `need_reference`: no trial aligned with its reference; without: not even an estimator stream) or
    another unit than `unit_id` recorded it; a warning if its purpose is not `purpose`."""
    from pipeline.config import IngestParams, ResampleParams
    from pipeline.signals.one_batch import read_batch

    batch = read_batch(
        batch_dir, section(IngestParams, "ingest", params), section(ResampleParams, "resample", params)
    )
    for problem in batch.problems:
        typer.echo(str(problem))
    if batch.unit_id is None:
        raise fail(f"{batch_dir}: nothing usable ({len(batch.problems)} problem(s)); fix them and run again")
    if unit_id is not None and unit_id != batch.unit_id:
        raise fail(
            f"{batch_dir} was recorded by unit {batch.unit_id!r} (batch.yaml sensor.unit_id), not {unit_id!r}"
        )
    if purpose is not None and batch.purpose != purpose:
        typer.echo(
            f"warning: {batch_dir}: purpose {batch.purpose!r}, not {purpose!r}: calibrating anyway", err=True
        )
    if batch.rows.empty and (need_reference or batch.estimator_only.empty):
        for line in batch.set_aside:
            typer.echo(f"set aside {line}")
        raise fail(f"{batch_dir}: no trial could be aligned and resampled")
    return batch
