"""`calibrate` stage: every new estimator unit's calibration, fitted through the frozen shared models.

Input: `DATA_DIR/calibration/<angle>.parquet` (the split stage's calibration rows, from batches with
`purpose: calibration`; `front_ends.json` beside them: each unit's declared circuit, which its rows
are read through and its document records) and `MODELS_DIR/<kind>/<angle>/model.pt`. Output:
`OUT_DIR/<unit_id>.json` per unit (`pipeline.calibration.unit`), which predict applies to that
unit's rows and register stores in MLflow. A calibration batch never trains or scores the shared models.

Usage: `python -m pipeline.execution.run calibrate DATA_DIR MODELS_DIR OUT_DIR [--params params.yaml]`.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import typer

from needlecue_runtime.unit_calibration import read_unit, write_unit
from needlecue_runtime.vocab import CALIBRATION, angle_name
from pipeline.calibration.rows import calibration_rows
from pipeline.calibration.unit import calibrate_unit
from pipeline.config import CalibrateParams, CuesParams, TrainParams, load_section
from pipeline.cues.unit_evidence import training_levels
from pipeline.dataset.splits import SplitFiles, front_ends
from pipeline.execution.workers import WORKERS
from pipeline.logs import setup
from pipeline.modelling.checkpoint import CHECKPOINT_FILE
from pipeline.modelling.predictor import load_predictor

_log = logging.getLogger("pipeline.stages").info  # not __name__: a stage runs as __main__


def main(data_dir: Path, models_dir: Path, out_dir: Path, params: Path = Path("params.yaml")) -> None:
    """Fit and write the calibration of every unit that has calibration rows."""
    setup("calibrate")
    p = load_section(CalibrateParams, "calibrate", params)
    train = load_section(TrainParams, "train", params)
    cues = load_section(CuesParams, "cues", params)
    angles = [angle_name(a) for a in train.angles]
    started = time.perf_counter()
    try:
        by_unit = calibration_rows(data_dir)
        circuits = front_ends(data_dir / CALIBRATION)
        files = SplitFiles(data_dir)  # a unit's cue evidence is at the training trials' loading levels
        levels = training_levels(files.by_angle("train"), cues, files.front_ends())
    except (FileNotFoundError, ValueError) as e:
        _log(f"error: {e}")
        raise typer.Exit(1) from e
    models = {
        kind: {
            a: load_predictor(models_dir / kind / a)
            for a in angles
            if (models_dir / kind / a / CHECKPOINT_FILE).is_file()
        }
        for kind in train.kinds
    }
    out_dir.mkdir(parents=True, exist_ok=True)
    written = set()
    for unit_id, rows in by_unit.items():
        doc = calibrate_unit(
            unit_id, rows, models, angles, p, _log, cues, circuits.get(unit_id), levels, workers=WORKERS
        )
        path = write_unit(doc, out_dir)
        written.add(path.name)
        unit = read_unit(path)  # what was written, as every reader reads it
        missing = (
            f"; no calibration insertion at {', '.join(unit.angles_missing)}°" if unit.angles_missing else ""
        )
        _log(f"{unit_id}: {len(unit.trials)} trial(s) at {', '.join(unit.angles_used) or 'no'}°{missing}")
        for s in unit.set_aside:
            _log(f"{unit_id}: set aside {s.file}: {s.reason}")
    for stale in sorted(out_dir.glob("*.json")):
        if stale.name not in written:
            stale.unlink()
    if not by_unit:
        _log(f"no calibration batch under {data_dir} (batches with purpose: calibration)")
    _log(f"{len(by_unit)} unit(s) calibrated in {time.perf_counter() - started:.1f} s -> {out_dir}")


if __name__ == "__main__":
    typer.run(main)
