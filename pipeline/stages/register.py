"""`register` stage: track every trained model in MLflow and register the best one per angle.

1. Tracking (`pipeline.registry.tracking`): each model is one run of the experiment `needle-force`.
2. Registering (`pipeline.registry.versions`, rule in `pipeline.registry.champion`): per angle, the
   best deployable candidate becomes a version of `needle-force-<angle>`, `@champion` only if it
   beats the current champion on today's external set, else `@challenger`.
3. Units (`pipeline.registry.calibrations`): each `CAL_DIR/<unit_id>.json` (the calibrate stage's) becomes a
   version of `needle-unit-<unit_id>` with the alias `@current`, unless those exact bytes already are
   one; a unit whose calibration was made with other models than today's champions is reported as
   stale ("run needlecue calibrate"), never an error.
4. `OUT_JSON` records per angle what was registered and promoted, and per unit its version (no run ids
   or paths, so a fresh store gives the same file).

Scores come from the predict stage's `PRED_DIR`; the store is `$MLFLOW_TRACKING_URI` or the
project's `mlflow.db` (`needlecue_runtime.registry.store`).

Usage: `python -m pipeline.execution.run register MODELS_DIR DATA_DIR PRED_DIR CAL_DIR REPORTS_DIR OUT_JSON
[--params params.yaml]`.
"""

from __future__ import annotations

import logging
from pathlib import Path

import typer

from needlecue_runtime.registry.store import RegistryUnreachable
from pipeline.config import RegisterParams, load_section
from pipeline.logs import setup
from pipeline.registry.versions import register_all

_log = logging.getLogger("pipeline.stages").info  # not __name__: a stage runs as __main__


def main(
    models_dir: Path,
    data_dir: Path,
    pred_dir: Path,
    cal_dir: Path,
    reports_dir: Path,
    out_json: Path,
    params: Path = Path("params.yaml"),
) -> None:
    """Track every trained model in MLflow, register the best per angle (champion / challenger) and
    every unit calibration in CAL_DIR (@current)."""
    setup("register")
    from mlflow.exceptions import MlflowException

    p = load_section(RegisterParams, "register", params)
    try:
        record = register_all(models_dir, data_dir, pred_dir, reports_dir, out_json, p, _log, cal_dir)
    except (RegistryUnreachable, FileNotFoundError, ValueError) as e:
        _log(f"error: {e}")
        raise typer.Exit(1) from e
    except MlflowException as e:  # the store answered, then failed: no alias moved after the failure
        _log(f"error: MLflow registry ({e.error_code}): {e.message}")
        raise typer.Exit(1) from e
    new_units = sorted(u for u, e in record["units"].items() if e["action"] == "registered")
    _log(
        f"registered {len(record['registered'])} angle(s), promoted {len(record['promoted'])}, "
        f"{len(new_units)} new unit calibration(s) of {len(record['units'])}, "
        f"{len(record['stale_units'])} stale -> {out_json}"
    )


if __name__ == "__main__":
    typer.run(main)
