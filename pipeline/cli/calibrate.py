"""`needlecue calibrate`: a new estimator unit calibrated through today's champions and registered."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer

from pipeline.cli.checked_batch import checked_batch
from pipeline.cli.params import ParamsOption, section
from pipeline.exits import fail


def _print_calibration(doc: dict[str, Any], champions: dict[str, Any], aside: list[str]) -> None:
    """Loss before and after per kind, the angles used and missing, what was set aside, and which
    champions the calibration does not cover."""
    from needlecue_runtime.unit_calibration import parse_unit
    from pipeline.registry.calibrations import uncovered_angles

    typer.echo(f"unit {doc['unit_id']}: {len(doc['trials'])} trial(s) of {', '.join(doc['batches']) or '-'}")
    for kind, t in sorted(doc["transforms"].items()):
        kept = f"; identity kept: {t['identity_kept']}" if t.get("identity_kept") else ""
        through = ", ".join(t.get("fitted_through") or [])
        typer.echo(
            f"  {kind}: loss {t['loss_before']:.4f} -> {t['loss_after']:.4f} (through {through}°){kept}"
        )
    used, missing = ", ".join(doc["angles_used"]) or "-", ", ".join(doc["angles_missing"]) or "-"
    typer.echo(f"angles used: {used}; missing: {missing}")
    for line in [*aside, *(f"{s['file']}: {s['reason']}" for s in doc["set_aside"])]:
        typer.echo(f"set aside {line}")
    for angle in uncovered_angles(parse_unit(doc, "the calibration"), champions):
        kind = champions[angle]["kind"]
        typer.echo(
            f"not calibrated: the {kind} champion at {angle}° (no usable trial where {kind} is champion)"
        )


def calibrate(
    batch_dir: Annotated[
        Path, typer.Argument(help="the unit's calibration batch: one rig-log/1 batch folder")
    ],
    unit_id: Annotated[
        str | None,
        typer.Option("--unit-id", help="check that this unit recorded the batch (batch.yaml sensor.unit_id)"),
    ] = None,
    params: ParamsOption = Path("params.yaml"),
    tracking_uri: Annotated[
        str | None,
        typer.Option("--tracking-uri", help="MLflow store (default: $MLFLOW_TRACKING_URI or mlflow.db)"),
    ] = None,
    dry_run: Annotated[bool, typer.Option("--dry-run", help="fit and print, register nothing")] = False,
) -> None:
    """Calibrate an estimator unit from its short calibration batch, through today's champions
    (needle-force-<angle>@champion), and register it as needle-unit-<unit>@current for the simulator.

    The batch is checked like `needlecue check` (problems printed as file:line), then ingested and
    resampled in a temp folder; each champion is loaded from the checkpoint its run logged. Exit 1:
    nothing usable in the batch, another unit than --unit-id, or nothing to calibrate; 2: not a folder,
    or the registry is unreachable.
    """
    from mlflow.exceptions import MlflowException

    from needlecue_runtime.registry import mlflow_env, store
    from needlecue_runtime.unit_calibration import parse_unit
    from pipeline.calibration.unit import calibrate_unit
    from pipeline.config import CalibrateParams
    from pipeline.registry import calibrations

    def say(message: str) -> None:
        typer.echo(f"calibrate: {message}", err=True)

    if not batch_dir.is_dir():
        raise fail(f"not a folder: {batch_dir}", 2)
    from needlecue_runtime.vocab import CALIBRATION

    batch = checked_batch(batch_dir, unit_id, params, CALIBRATION)
    unit, rows, aside, front_end = batch.unit_id, batch.rows, batch.set_aside, batch.front_end
    with mlflow_env.patience(write=True):  # MLflow's HTTP timeouts, for as long as the registry is used
        try:
            client = store.connect(tracking_uri, must_exist=True, write=True)  # it registers the calibration
            champions = calibrations.champion_models(client, log=say)
            if not champions:
                where = client.tracking_uri
                raise fail(f"the registry at {where} has no readable needle-force-<angle>@champion")
            models = calibrations.champion_predictors(client, champions, say)
        except store.RegistryUnreachable as e:
            raise fail(str(e), 2) from e
        except MlflowException as e:
            raise fail(f"MLflow registry ({e.error_code}): {e.message}") from e
        for kind, by_angle in models.items():
            for angle, predictor in list(by_angle.items()):
                lacking = [c for c in predictor.channels if c not in rows.columns]
                if lacking:
                    say(
                        f"the {kind} champion at {angle}° reads {list(predictor.channels)}: "
                        f"the batch has no {lacking}"
                    )
                    del by_angle[angle]
        p = section(CalibrateParams, "calibrate", params)
        doc = calibrate_unit(unit, rows, models, list(champions), p, say, front_end=front_end)
        _print_calibration(doc, champions, aside)
        if not doc["transforms"]:
            raise fail("nothing calibrated: no usable calibration trial at an angle with a champion")
        name = store.unit_model_name(unit)
        if dry_run:
            typer.echo(f"dry run: {name} not registered")
            return
        try:
            unit_doc = parse_unit(doc, "the calibration")
            entry = calibrations.register_unit(client, unit_doc, calibrations.document_bytes(doc), say)
        except MlflowException as e:
            raise fail(f"MLflow registry ({e.error_code}): {e.message}") from e
        state = "registered" if entry["action"] == "registered" else "already registered"
        typer.echo(f"{state}: {name} version {entry['version']} (@{store.UNIT_ALIAS})")
