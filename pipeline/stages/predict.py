"""`predict` stage: every trained model on every processed split of every angle, computed once.

Input: `DATA_DIR/<angle>/{train,val,test,external}.parquet`, `MODELS_DIR/<kind>/<angle>/model.pt`
for the `train` section's angles and kinds, and the units' calibrations `CAL_DIR/<unit>.json` (the
calibrate stage's): a calibrated unit's external rows are predicted through its transform. Output:
`OUT_DIR/<kind>/<angle>.parquet` (see `pipeline.modelling.prediction_store`), which evaluate, cues,
report and register read, and `OUT_DIR/inputs.json` (what each model reads and how that was
chosen, for the report). A unit that declares its own circuit (`front_ends.json`) is read through it.

Usage: `python -m pipeline.execution.run predict DATA_DIR MODELS_DIR CAL_DIR OUT_DIR [--params params.yaml]`.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import typer

from pipeline.calibration.apply import unit_transforms
from pipeline.config import TrainParams, load_section
from pipeline.logs import setup
from pipeline.modelling.split_predictions import predict_all

_log = logging.getLogger("pipeline.stages").info  # not __name__: a stage runs as __main__


def main(
    data_dir: Path, models_dir: Path, cal_dir: Path, out_dir: Path, params: Path = Path("params.yaml")
) -> None:
    """Predict every model on every split and write the predictions as Parquet."""
    setup("predict")
    train = load_section(TrainParams, "train", params)
    started = time.perf_counter()
    try:
        units = unit_transforms(cal_dir, models_dir, train.kinds, train.angles)
        for unit in sorted({u for found in units.values() for u in found}):
            models = sorted(f"{k}/{a}" for (k, a), found in units.items() if unit in found)
            _log(f"unit {unit}: external rows through its calibration for {len(models)} model(s)")
        done = predict_all(data_dir, models_dir, out_dir, train.kinds, train.angles, _log, units=units)
    except (FileNotFoundError, ValueError) as e:
        _log(f"error: {e}")
        raise typer.Exit(1) from e
    if not done:
        _log(f"warning: no trained model found under {models_dir}")
    _log(f"{len(done)} model(s) predicted in {time.perf_counter() - started:.1f} s -> {out_dir}")


if __name__ == "__main__":
    typer.run(main)
