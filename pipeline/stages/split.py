"""`split` stage: per angle, split the resampled trials into train/val/test by trial, with
held-out batches as the external set (`pipeline.dataset.split`).

Input: the resample stage's `IN_DIR/<batch_id>.{parquet,json}`. Output: `OUT_DIR/<angle>/
{train,val,test,external}.parquet`, `OUT_DIR/calibration/<angle>.parquet` (the trials of
`purpose: calibration` batches, never in a split), `front_ends.json` next to them (each unit's
declared circuit) and `OUT_DIR/manifest.json`.

Usage: `python -m pipeline.execution.run split IN_DIR OUT_DIR [--params params.yaml]`.
"""

from __future__ import annotations

import logging
from pathlib import Path

import typer

from pipeline.config import SplitParams, TrainParams, load_section
from pipeline.dataset.split import run
from pipeline.logs import setup

_log = logging.getLogger("pipeline.stages").info  # not __name__: a stage runs as __main__


def main(in_dir: Path, out_dir: Path, params: Path = Path("params.yaml")) -> None:
    """Split the resampled trials per angle into train/val/test/external files."""
    setup()
    try:
        trained = load_section(TrainParams, "train", params).angles
        run(in_dir, out_dir, load_section(SplitParams, "split", params), trained=trained, log=_log)
    except (OSError, ValueError) as e:  # missing metadata, mixed grid rates: one clear line, not a traceback
        _log(f"split: error: {e}")
        raise typer.Exit(1) from e


if __name__ == "__main__":
    typer.run(main)
