"""`needlecue replay`: a recorded trial, batch or live session through the simulator's client again."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from pipeline.cli.checked_batch import checked_batch
from pipeline.exits import fail
from pipeline.live.commands import UnverifiedOption, load_client


def replay(
    trial: Annotated[
        Path,
        typer.Argument(
            help="a processed parquet file (data/processed/15/external.parquet), a raw rig-log/1 trial "
            "file (<batch>/<trial>.fsr.csv, .ref.csv, .ref.tdms, or a .csv.gz) or a raw batch folder"
        ),
    ],
    angle: Annotated[
        float | None, typer.Option("--angle", help="preset insertion angle (deg) whose model is fetched")
    ] = None,
    trial_id: Annotated[
        str | None, typer.Option("--trial", help="BATCH/TRIAL_ID to replay (default: the file's first)")
    ] = None,
    alias: Annotated[str, typer.Option("--alias", help="registry alias of the model")] = "champion",
    model_dir: Annotated[
        Path | None, typer.Option("--model-dir", help="an already-fetched model folder (skips the registry)")
    ] = None,
    unit_id: Annotated[
        str | None,
        typer.Option("--unit-id", help="the estimator unit that recorded it: its calibration is applied"),
    ] = None,
    out: Annotated[
        Path | None, typer.Option("--out", help="PNG to write (default: replay-<batch>-<trial>.png)")
    ] = None,
    unverified: UnverifiedOption = False,
) -> None:
    """Replay a recorded trial through the simulator's client as if live: cue timeline, RMSE and a plot.

    A raw trial (either of its files, in any form ingest reads: CSV, gzip-compressed CSV, a TDMS reference)
    or batch folder is checked, ingested and resampled as the pipeline would (params.yaml), and its
    batch.yaml names the unit when --unit-id does not.

    With --unit-id the unit's registered calibration (needle-unit-<unit>@current) is applied, as on the
    simulator; without it, or when it was made with other models, the force is uncalibrated and there
    are no cues. A --model-dir whose graph or description is not what was registered is refused
    (--unverified runs it anyway, loudly). Exit 1 on a bad input (file, trial, model folder, stream
    mismatch), 2 if the registry is unreachable and there is no local copy of the model.
    """
    import pandas as pd

    from needlecue_client import replay as rp
    from needlecue_client.force import CALIBRATE_FIX
    from needlecue_runtime.registry.store import RegistryUnreachable
    from needlecue_runtime.vocab import channels_of, rate_hz
    from pipeline.rig.format import BATCH_FILE, STREAM_SUFFIXES

    if angle is None and model_dir is None:
        raise fail("give --angle (the preset angle whose model to fetch) or --model-dir")
    from pipeline.live.recording import is_session

    if trial.is_dir() and is_session(trial):
        _replay_session(trial, angle, alias, model_dir, unit_id, unverified)
        return
    suffix = next((s for s in STREAM_SUFFIXES if trial.name.endswith(s)), None)
    unaligned: set[str] = set()  # trials replayed from their estimator stream alone
    batch_aside: list[str] = []
    if trial.is_dir() or suffix:  # rig-log/1: checked, ingested and resampled like the pipeline does
        batch_dir = trial.parent if suffix else trial
        if not (batch_dir / BATCH_FILE).is_file():
            raise fail(f"{batch_dir}: not a rig-log/1 batch folder (no {BATCH_FILE})")
        if suffix:
            trial_id = trial_id or f"{batch_dir.name}/{trial.name.removesuffix(suffix)}"
        batch = checked_batch(batch_dir, None, Path("params.yaml"), need_reference=False)
        unit_id = unit_id or batch.unit_id
        frame = pd.concat([batch.rows, batch.estimator_only], ignore_index=True)
        if not batch.estimator_only.empty:
            unaligned = set(batch.estimator_only["trial_id"].astype(str))
        batch_aside = batch.set_aside
    elif trial.suffix == ".parquet":
        try:
            frame = pd.read_parquet(trial)
        except (OSError, ValueError) as e:  # missing file, not parquet
            raise fail(f"cannot read {trial}: {e}") from e
    else:
        raise fail(
            f"{trial}: not a processed parquet file, a rig-log/1 trial file (<trial>.fsr.csv, "
            "<trial>.ref.csv, either gzip-compressed as .csv.gz, or <trial>.ref.tdms) or a batch folder"
        )
    if frame.empty or not {"batch_id", "trial_id", "t_s"} <= set(frame.columns):
        raise fail(f"{trial}: not a processed split file (needs rows and batch_id, trial_id, t_s)")
    ids = frame[["batch_id", "trial_id"]].astype(str).drop_duplicates()
    keys = [f"{b}/{t}" for b, t in ids.itertuples(index=False)]
    key = trial_id or keys[0]
    if key not in keys:
        shown = ", ".join(keys[:5]) + (", ..." if len(keys) > 5 else "")
        raise fail(f"{trial}: no trial {key!r} (BATCH/TRIAL_ID); it has {len(keys)}: {shown}")
    batch, tid = key.split("/", 1)
    rows = frame[(frame["batch_id"].astype(str) == batch) & (frame["trial_id"].astype(str) == tid)]
    if tid in unaligned:
        rows = rows.dropna(axis=1, how="all")  # the aligned trials' force columns: not this one's
        line = next((a for a in batch_aside if a.startswith(f"{key}: ")), "")
        why = line.removeprefix(f"{key}: ").removeprefix("set aside: ") or "set aside by resample"
        typer.echo(
            f"warning: {key}: its reference could not be aligned ({why}); replaying the estimator "
            "stream alone, no RMSE",
            err=True,
        )

    try:
        client = load_client(angle, alias, model_dir, unit_id, unverified=unverified)
        client.check_stream(channels_of(rows), rate_hz(rows["t_s"].to_numpy()))
        result = rp.replay(rows, client)
    except RegistryUnreachable as e:
        raise fail(str(e), 2) from e
    except (FileNotFoundError, ValueError, LookupError) as e:  # incl. StreamMismatch, ModelNotFound
        raise fail(str(e)) from e

    typer.echo(f"{key}: {len(result)} samples through {client.name}, preset angle {client.angle_deg:g}°")
    if client.calibrated:
        cal = client.calibration or {}
        source = f"{cal['name']} v{cal.get('version')}" if cal.get("name") else cal.get("path", "given")
        typer.echo(f"unit {client.unit_id}: calibrated ({source})")
    else:
        fix = f"to calibrate the unit, {CALIBRATE_FIX}" if unit_id else "--unit-id names the unit"
        typer.echo(f"uncalibrated: {client.uncalibrated_reason}; {fix}")
    changes = rp.cue_changes(result)
    if changes.empty:
        why = "the model was registered without a cue pack"
        if client.metadata.get("cues") is not None:
            why = "the unit is not calibrated for this model (cues need its calibration)"
        typer.echo(f"no cues: {why}")
    for row in changes.itertuples(index=False):
        est = "     -" if pd.isna(row.angle_est_deg) else f"{row.angle_est_deg:5.0f}°"
        typer.echo(f"{row.t_s:8.2f} s  {row.cue:<8}  angle {est}  {row.reason}")
    errors = rp.rmse(result)
    summary = ", ".join(f"{c} {v:.4f} N" for c, v in errors.items()) if errors else "no reference force"
    typer.echo(f"RMSE vs reference: {summary}")
    png = out or Path(f"replay-{batch}-{tid}.png")
    rp.plot_replay(result, png, f"{key} through {client.name}, preset {client.angle_deg:g}°")
    typer.echo(f"wrote {png}")


def _replay_session(
    folder: Path,
    angle: float | None,
    alias: str,
    model_dir: Path | None,
    unit_id: str | None,
    unverified: bool = False,
) -> None:
    """`needlecue replay` of a live session's recording: its lines through the same chain again."""
    from needlecue_runtime.registry.store import RegistryUnreachable
    from pipeline.live.app import replay_session
    from pipeline.live.recording import read_meta, read_trials

    meta = read_meta(folder)
    recorded_unit = (meta.get("sensor") or {}).get("unit_id")
    unit_id = unit_id or (recorded_unit if recorded_unit != "unknown" else None)
    try:
        cues = bool((meta.get("live") or {}).get("cues_uncalibrated"))  # as the live session was told
        client = load_client(angle, alias, model_dir, unit_id, cues, unverified)
        summary = replay_session(folder, client)
    except RegistryUnreachable as e:
        raise fail(str(e), 2) from e
    except (FileNotFoundError, ValueError, LookupError) as e:
        raise fail(str(e)) from e
    recorded = {t["trial_id"]: t["cues"].split() for t in read_trials(folder)}
    typer.echo(f"{folder}: live session through {client.name}, preset angle {client.angle_deg:g}°")
    same = True
    for ins in summary["insertions"]:
        live = recorded.get(ins["trial_id"])
        same &= live == ins["cues"]
        note = "as live" if live == ins["cues"] else f"live showed {' -> '.join(live or ['nothing'])}"
        typer.echo(f"insertion {ins['number']} ({ins['trial_id']}): {' -> '.join(ins['cues'])} ({note})")
    typer.echo(f"stream: {summary['counts']}")
    if not same or len(recorded) != len(summary["insertions"]):
        raise fail("the replay differs from what the live session showed (another model or calibration?)")
