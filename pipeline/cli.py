"""`needlecue`: the commands a person runs by hand (the stages themselves run under `dvc repro`)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

app = typer.Typer(add_completion=False, no_args_is_help=True, help=__doc__)

ParamsOption = Annotated[Path, typer.Option("--params", help="params.yaml to read settings from")]


@app.command()
def simulate(
    out_dir: Annotated[Path, typer.Argument(help="folder to write rig-log/1 batches into (new or empty)")],
    params: ParamsOption = Path("params.yaml"),
) -> None:
    """Write simulated rig-log/1 batches, as configured in params.yaml's `simulate` section."""
    from pipeline.config import SimulateParams, load_section
    from pipeline.sim import rig as stage

    p = load_section(SimulateParams, "simulate", params) if params.exists() else SimulateParams()
    try:
        ids = stage.run(p.model_copy(update={"enabled": True}), out_dir)
    except FileExistsError as e:
        typer.echo(f"error: {e}", err=True)
        raise typer.Exit(2) from e
    typer.echo(f"wrote {len(ids)} batches to {out_dir}")


@app.command("simulate-batch")
def simulate_batch(
    raw_dir: Annotated[Path, typer.Argument(help="the raw folder to drop the batch into, e.g. data/raw")],
    batch_id: Annotated[str, typer.Argument(help="the new batch's id (its folder name)")],
    angles: Annotated[str, typer.Option(help="comma-separated insertion angles (deg)")] = "15",
    trials: Annotated[int, typer.Option(help="trials (tissue points) per angle")] = 7,
    params: ParamsOption = Path("params.yaml"),
) -> None:
    """Simulate one new tissue cast recorded with the same estimator, as a lab would deliver it."""
    from pipeline.config import SimulateParams, load_section
    from pipeline.sim import rig as stage

    p = load_section(SimulateParams, "simulate", params) if params.exists() else SimulateParams()
    try:
        angle_list = tuple(float(a) for a in angles.split(","))
        n = stage.write_new_batch(p, raw_dir, batch_id, angle_list, trials)
    except ValueError as e:
        typer.echo(f"error: --angles {angles!r}: {e}", err=True)
        raise typer.Exit(2) from e
    except FileExistsError as e:
        typer.echo(f"error: {e}", err=True)
        raise typer.Exit(2) from e
    typer.echo(f"wrote {raw_dir / batch_id}: {len(angle_list) * trials} trials, {n} estimator samples")


@app.command()
def retrain(
    project: Annotated[Path, typer.Option(help="the project folder (holds dvc.yaml)")] = Path("."),
    params: ParamsOption = Path("params.yaml"),
) -> None:
    """Retrain on new or changed batches, register, promote by the champion rule; safe from cron.

    Exit 0 nothing new, 1 failed, 2 retrained, 3 retrained with batches set aside, 4 another retrain runs.
    """
    from pipeline.retrain import retrain as run

    code, _report = run(project.resolve(), params)
    raise typer.Exit(code)


@app.command()
def check(
    raw_dirs: Annotated[list[Path], typer.Argument(help="raw folders, each holding batch folders")],
    params: ParamsOption = Path("params.yaml"),
) -> None:
    """Check rig-log/1 folders without running the pipeline; exit 1 if anything would be set aside."""
    from pipeline.config import IngestParams, load_section
    from pipeline.rig.ingest import check_folders

    p = load_section(IngestParams, "ingest", params) if params.exists() else IngestParams()
    missing = [d for d in raw_dirs if not d.is_dir()]
    if missing:
        typer.echo(f"error: not a folder: {', '.join(map(str, missing))}", err=True)
        raise typer.Exit(2)
    problems = check_folders(raw_dirs, p)
    for problem in problems:
        typer.echo(str(problem))
    typer.echo(f"{len(problems)} problem(s) in {', '.join(map(str, raw_dirs))}", err=True)
    raise typer.Exit(1 if problems else 0)


@app.command()
def replay(
    trial: Annotated[
        Path, typer.Argument(help="processed parquet file, e.g. data/processed/15/external.parquet")
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
    out: Annotated[
        Path | None, typer.Option("--out", help="PNG to write (default: replay-<batch>-<trial>.png)")
    ] = None,
) -> None:
    """Replay a recorded trial through the simulator's client as if live: cue timeline, RMSE and a plot.

    Exit 1 on a bad input (file, trial, model folder, stream mismatch), 2 if the registry is unreachable
    and there is no local copy of the model.
    """
    import pandas as pd

    from pipeline.client import ForceClient
    from pipeline.client import replay as rp
    from pipeline.registry.store import RegistryUnreachable
    from pipeline.vocab import channels_of, rate_hz

    def fail(message: str, code: int = 1) -> typer.Exit:
        typer.echo(f"error: {message}", err=True)
        return typer.Exit(code)

    if angle is None and model_dir is None:
        raise fail("give --angle (the preset angle whose model to fetch) or --model-dir")
    try:
        frame = pd.read_parquet(trial)
    except (OSError, ValueError) as e:  # missing file, not parquet
        raise fail(f"cannot read {trial}: {e}") from e
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

    try:
        if model_dir is not None:
            client = ForceClient.from_dir(model_dir)
            if angle is not None and client.angle_deg != angle:
                raise fail(f"--angle {angle:g} but the model in {model_dir} is for {client.angle_deg:g}°")
        else:
            assert angle is not None
            client = ForceClient.from_registry(angle, alias)
        client.check_stream(channels_of(rows), rate_hz(rows["t_s"].to_numpy()))
        result = rp.replay(rows, client)
    except RegistryUnreachable as e:
        raise fail(str(e), 2) from e
    except (FileNotFoundError, ValueError, LookupError) as e:  # incl. StreamMismatch, ModelNotFound
        raise fail(str(e)) from e

    typer.echo(f"{key}: {len(result)} samples through {client.name}, preset angle {client.angle_deg:g}°")
    changes = rp.cue_changes(result)
    if changes.empty:
        typer.echo("no cues: the model was registered without a cue pack")
    for row in changes.itertuples(index=False):
        est = "     -" if pd.isna(row.angle_est_deg) else f"{row.angle_est_deg:5.0f}°"
        typer.echo(f"{row.t_s:8.2f} s  {row.cue:<8}  angle {est}  {row.reason}")
    errors = rp.rmse(result)
    summary = ", ".join(f"{c} {v:.4f} N" for c, v in errors.items()) if errors else "no reference force"
    typer.echo(f"RMSE vs reference: {summary}")
    png = out or Path(f"replay-{batch}-{tid}.png")
    rp.plot_replay(result, png, f"{key} through {client.name}, preset {client.angle_deg:g}°")
    typer.echo(f"wrote {png}")


@app.command()
def rollback(
    angle: Annotated[float, typer.Argument(help="insertion angle (deg) of the registered model")],
    to: Annotated[
        int | None, typer.Option("--to", help="version to make champion (default: the one it replaced)")
    ] = None,
) -> None:
    """Move `needle-force-<angle>@champion` back to an earlier version (exit 1: refused, 2: offline)."""
    from pipeline.registry.store import RegistryUnreachable, model_name
    from pipeline.registry.versions import rollback as do_rollback

    try:
        old, new = do_rollback(angle, to)
    except RegistryUnreachable as e:
        typer.echo(f"error: {e}", err=True)
        raise typer.Exit(2) from e
    except ValueError as e:
        typer.echo(f"error: {e}", err=True)
        raise typer.Exit(1) from e
    typer.echo(f"{model_name(angle)}@champion: version {old} -> {new}")


if __name__ == "__main__":
    app()
