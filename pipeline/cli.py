"""`needlecue`: the commands a person runs by hand (the stages themselves run under `dvc repro`)."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Annotated, Any

import typer

from pipeline.exits import fail
from pipeline.live import commands as live_commands
from pipeline.live.commands import UnverifiedOption, load_client
from pipeline.team import commands as team_commands

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
    unit: Annotated[
        str | None,
        typer.Option(help="the estimator unit that records it (default: the first of simulate.units)"),
    ] = None,
    purpose: Annotated[
        str, typer.Option(help="batch.yaml purpose: training, or calibration (kept out of the splits)")
    ] = "training",
    params: ParamsOption = Path("params.yaml"),
) -> None:
    """Simulate one new tissue cast recorded by one estimator unit, as a lab would deliver it."""
    from pipeline.config import SimulateParams, load_section
    from pipeline.sim import rig as stage

    p = load_section(SimulateParams, "simulate", params) if params.exists() else SimulateParams()
    try:
        angle_list = tuple(float(a) for a in angles.split(","))
    except ValueError as e:
        typer.echo(f"error: --angles {angles!r}: {e}", err=True)
        raise typer.Exit(2) from e
    try:
        n = stage.write_new_batch(p, raw_dir, batch_id, angle_list, trials, unit_id=unit, purpose=purpose)
    except (ValueError, FileExistsError) as e:
        typer.echo(f"error: {e}", err=True)
        raise typer.Exit(2) from e
    typer.echo(f"wrote {raw_dir / batch_id}: {len(angle_list) * trials} trials, {n} estimator samples")


@app.command()
def repro(
    targets: Annotated[
        list[str] | None, typer.Argument(help="stages to reproduce, with what they depend on (default: all)")
    ] = None,
    jobs: Annotated[
        int | None,
        typer.Option("--jobs", "-j", min=1, help="stages at a time (default: the CPUs this process has)"),
    ] = None,
    project: Annotated[Path, typer.Option(help="the project folder (holds dvc.yaml)")] = Path("."),
) -> None:
    """`dvc repro` on every core: stages that do not depend on each other run side by side, each
    through `dvc repro --single-item`. The same outputs, byte for byte, as `dvc repro`.

    Exit 0 done (or nothing to do), 1 a stage failed (the stages already running finish first) or no
    such stage, 2 no DVC project there.
    """
    from dvc.exceptions import DvcException

    from pipeline.execution import repro as parallel
    from pipeline.execution.workers import usable_cpus

    root = project.resolve()
    try:
        plan = parallel.dvc_plan(root, targets or ())
    except ValueError as e:
        raise fail(str(e)) from e
    except DvcException as e:  # not a DVC project, a dvc.yaml DVC cannot read, ...
        raise fail(f"{root}: {e}", 2) from e
    if not plan.order:
        typer.echo("Data and pipelines are up to date.")
        return
    n = jobs or usable_cpus()
    typer.echo(f"{len(plan.order)} stage(s) to consider, up to {n} at a time")
    t0 = time.perf_counter()
    outcome = parallel.reproduce(root, plan, n)
    seconds = time.perf_counter() - t0
    if outcome.code:
        typer.echo("\n".join(outcome.tail), err=True)
        failed = ", ".join(outcome.failed)
        raise fail(f"stage {failed} failed after {seconds:.0f} s (the tail of its output is above)")
    busy = sum(end - start for start, end in outcome.spans.values())
    typer.echo(
        f"ran {len(outcome.ran)} of {len(plan.order)} stage(s) in {seconds:.1f} s "
        f"({busy:.1f} s of stages side by side)"
        + (". To track the changes with git, run: git add dvc.lock" if outcome.ran else "")
    )


@app.command()
def retrain(
    project: Annotated[Path, typer.Option(help="the project folder (holds dvc.yaml)")] = Path("."),
    params: ParamsOption = Path("params.yaml"),
) -> None:
    """Retrain on new or changed batches, register, promote by the champion rule; safe from cron.

    Exit 0 nothing new, 1 failed, 2 retrained, 3 retrained with batches set aside, 4 another retrain runs.
    """
    from pipeline.logs import setup
    from pipeline.retrain import retrain as run

    setup("retrain")
    code, _report = run(project.resolve(), params)
    raise typer.Exit(code)


@app.command()
def check(
    raw_dirs: Annotated[list[Path], typer.Argument(help="raw folders, each holding batch folders")],
    params: ParamsOption = Path("params.yaml"),
    ledger: Annotated[
        Path, typer.Option(help="the last `dvc repro`'s ledger, for where the trials ended up")
    ] = Path("reports/ledger/ledger.json"),
) -> None:
    """Check rig-log/1 folders without running the pipeline: every problem, then every batch's trials
    (pass ingest or set aside, and where the last run's ledger placed them); exit 1 if anything would
    be set aside."""
    from pipeline.config import IngestParams, load_section
    from pipeline.rig.ingest import check_batches

    p = load_section(IngestParams, "ingest", params) if params.exists() else IngestParams()
    missing = [d for d in raw_dirs if not d.is_dir()]
    if missing:
        typer.echo(f"error: not a folder: {', '.join(map(str, missing))}", err=True)
        raise typer.Exit(2)
    checked = check_batches(raw_dirs, p)
    problems = [problem for c in checked for problem in c.problems]
    for problem in problems:
        typer.echo(str(problem))
    last_run, repeats = _ledger_places(ledger), _repeats(checked)
    for c in checked:
        _print_trials(c, last_run, repeats)
    typer.echo(f"{len(problems)} problem(s) in {', '.join(map(str, raw_dirs))}", err=True)
    if repeats:
        typer.echo(f"{len(repeats)} trial(s) repeat another's recording: split will set them aside", err=True)
    raise typer.Exit(1 if problems or repeats else 0)


def _repeats(checked: list[Any]) -> dict[tuple[str, str], str]:
    """{(batch, trial): the batch/trial it repeats}: what the split stage will set aside as a copy."""
    from pipeline.rig.repeats import repeats

    hashes = {(c.batch_id, t): h for c in checked for t, h in c.samples_sha256.items()}
    return {key: "/".join(original) for key, original in repeats(hashes).items()}


def _ledger_places(path: Path) -> dict[tuple[Path, str], dict[str, Any]]:
    """{(batch folder, trial): its ledger entry} from a written ledger; empty if there is none.
    Folders are resolved from here, as the pipeline's are from the project folder."""
    import json

    try:
        doc = json.loads(path.read_text())
        return {
            (Path(e["source"]).resolve(), str(e["trial_id"])): e for e in doc["entries"] if e.get("trial_id")
        }
    except (OSError, ValueError, KeyError, TypeError):
        return {}


def _print_trials(
    c: Any, last_run: dict[tuple[Path, str], dict[str, Any]], repeats: dict[tuple[str, str], str]
) -> None:
    """One batch's accounting: each trial passes ingest's checks or is set aside (the problems above
    say why); for a trial the last run's ledger knows, where it ended up."""
    from pipeline.reporting.ledger import entry_text
    from pipeline.vocab import one_line

    n = len(c.trials_accepted) + len(c.trials_set_aside)
    typer.echo(
        one_line(
            f"{c.batch_id} ({c.folder}): {n} trial(s), {len(c.trials_accepted)} pass ingest's checks, "
            f"{len(c.trials_set_aside)} set aside" + ("" if n else "; the batch is set aside as a whole")
        )
    )
    for trial in sorted([*c.trials_accepted, *c.trials_set_aside]):
        state = "passes ingest" if trial in c.trials_accepted else "set aside at ingest (problems above)"
        if (c.batch_id, trial) in repeats:
            state += f", but its samples are those of {repeats[c.batch_id, trial]}: split will set it aside"
        known = last_run.get((c.folder.resolve(), trial))
        typer.echo(f"  {trial}: {state}" + (f"; last dvc repro: {entry_text(known)}" if known else ""))


def _section(model: Any, name: str, params: Path) -> Any:
    """One params.yaml section, or its defaults when there is no params file (a simulator's machine)."""
    from pipeline.config import load_section

    return load_section(model, name, params) if params.exists() else model()


def _read_batch(
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
        batch_dir, _section(IngestParams, "ingest", params), _section(ResampleParams, "resample", params)
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


def _print_calibration(doc: dict[str, Any], champions: dict[str, Any], aside: list[str]) -> None:
    """Loss before and after per kind, the angles used and missing, what was set aside, and which
    champions the calibration does not cover."""
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
    for angle in uncovered_angles(doc, champions):
        kind = champions[angle]["kind"]
        typer.echo(
            f"not calibrated: the {kind} champion at {angle}° (no usable trial where {kind} is champion)"
        )


@app.command()
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

    from pipeline.calibration.unit import calibrate_unit
    from pipeline.config import CalibrateParams
    from pipeline.registry import calibrations, store

    def say(message: str) -> None:
        typer.echo(f"calibrate: {message}", err=True)

    if not batch_dir.is_dir():
        raise fail(f"not a folder: {batch_dir}", 2)
    from pipeline.vocab import CALIBRATION

    batch = _read_batch(batch_dir, unit_id, params, CALIBRATION)
    unit, rows, aside, front_end = batch.unit_id, batch.rows, batch.set_aside, batch.front_end
    with store.patience(write=True):  # MLflow's HTTP timeouts, for as long as the registry is used
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
        p = _section(CalibrateParams, "calibrate", params)
        doc = calibrate_unit(unit, rows, models, list(champions), p, say, front_end=front_end)
        _print_calibration(doc, champions, aside)
        if not doc["transforms"]:
            raise fail("nothing calibrated: no usable calibration trial at an angle with a champion")
        name = store.unit_model_name(unit)
        if dry_run:
            typer.echo(f"dry run: {name} not registered")
            return
        try:
            entry = calibrations.register_unit(client, doc, calibrations.document_bytes(doc), say)
        except MlflowException as e:
            raise fail(f"MLflow registry ({e.error_code}): {e.message}") from e
        state = "registered" if entry["action"] == "registered" else "already registered"
        typer.echo(f"{state}: {name} version {entry['version']} (@{store.UNIT_ALIAS})")


@app.command()
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

    from pipeline.client import replay as rp
    from pipeline.client.force import CALIBRATE_FIX
    from pipeline.registry.store import RegistryUnreachable
    from pipeline.rig.format import BATCH_FILE, STREAM_SUFFIXES
    from pipeline.vocab import channels_of, rate_hz

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
        batch = _read_batch(batch_dir, None, Path("params.yaml"), need_reference=False)
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
    from pipeline.live.app import replay_session
    from pipeline.live.recording import read_meta, read_trials
    from pipeline.registry.store import RegistryUnreachable

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


@app.command()
def rollback(
    angle: Annotated[float, typer.Argument(help="insertion angle (deg) of the registered model")],
    to: Annotated[
        int | None, typer.Option("--to", help="version to make champion (default: the one it replaced)")
    ] = None,
) -> None:
    """Move `needle-force-<angle>@champion` back to an earlier version (exit 1: refused, including by a
    read-only store or something that is not MLflow; 2: offline). Nothing changes unless it succeeds."""
    from pipeline.registry.store import NotMlflow, ReadOnlyStore, RegistryUnreachable, model_name
    from pipeline.registry.versions import rollback as do_rollback

    try:
        old, new = do_rollback(angle, to)
    except (NotMlflow, ReadOnlyStore, ValueError) as e:
        typer.echo(f"error: {e}", err=True)
        raise typer.Exit(1) from e
    except RegistryUnreachable as e:
        typer.echo(f"error: {e}", err=True)
        raise typer.Exit(2) from e
    typer.echo(f"{model_name(angle)}@champion: version {old} -> {new}")


@app.command()
def ui(
    port: Annotated[int, typer.Option(help="port of the UI (the project's sqlite store)")] = 5000,
    host: Annotated[str, typer.Option(help="address to bind (127.0.0.1: this machine only)")] = "127.0.0.1",
) -> None:
    """MLflow's UI on the registry, on the runs of every angle and model kind with their external and
    test NRMSE, best first. The project's sqlite store is served here until Ctrl-C; a tracking server
    (MLFLOW_TRACKING_URI) serves its own UI, and the link to it is printed. Exit 2: no registry."""
    import contextlib
    import os
    import signal
    import subprocess
    import sys
    import time
    import urllib.request

    from pipeline.registry import store
    from pipeline.registry.ui import is_server, runs_link, server_command

    uri = store.tracking_uri()
    try:
        with store.patience():
            client = store.connect(uri, must_exist=True)
            if is_server(uri):
                typer.echo(runs_link(client, uri))
                return
            link = runs_link(client, f"http://{host}:{port}")
    except store.RegistryUnreachable as e:
        raise fail(str(e), 2) from e
    # in a process group of its own, stopped whole: mlflow server runs uvicorn and job workers under it
    server = subprocess.Popen(server_command(uri, host, port), stdout=sys.stderr, start_new_session=True)
    # `kill` (SIGTERM) ends the UI as Ctrl-C does: through the `finally` below, which stops the server
    # (by default Python would die at once and leave the server running, orphaned)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(128 + signal.SIGTERM))
    try:
        deadline = time.monotonic() + 120
        while server.poll() is None and time.monotonic() < deadline:
            try:
                urllib.request.urlopen(f"http://{host}:{port}/health", timeout=2).close()
                break
            except OSError:
                time.sleep(0.5)
        if server.poll() is not None:
            raise fail(f"mlflow server exited with {server.returncode} (is port {port} taken?)")
        typer.echo(f"MLflow UI on {uri}, Ctrl-C to stop:\n{link}", err=True)
        typer.echo(link)
        server.wait()
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(server.pid, signal.SIGTERM)
        try:
            server.wait(timeout=30)
        except subprocess.TimeoutExpired:
            os.killpg(server.pid, signal.SIGKILL)
            server.wait(timeout=30)


@app.command("data-of")
def data_of(
    angle: Annotated[float, typer.Argument(help="insertion angle (deg) of the registered model")],
    version: Annotated[int, typer.Argument(help="the registered version")],
    pull: Annotated[bool, typer.Option(help="run `dvc pull` after writing dvc.lock")] = True,
) -> None:
    """Bring the exact data behind a registered version into this clone: its dvc.lock from the registry
    (checked against the version's tag), then `dvc pull` from the DVC remote. Check out the version's
    commit first (`git_commit` tag; the command says which)."""
    import subprocess
    import sys

    from pipeline.registry.provenance import ProvenanceError, restore_lock
    from pipeline.registry.store import RegistryUnreachable

    try:
        found = restore_lock(angle, version, Path.cwd())
    except (ProvenanceError, RegistryUnreachable) as e:
        raise fail(str(e)) from e
    typer.echo(
        f"{found['model']} v{version}: dvc.lock of run {found['run_id']} (commit {found['git_commit']})"
    )
    if pull:
        done = subprocess.run([sys.executable, "-m", "dvc", "pull"], check=False)
        if done.returncode != 0:
            raise fail(f"dvc pull failed (exit {done.returncode})", done.returncode)


app.add_typer(team_commands.team, name="team")
app.command("live")(live_commands.live)
app.command("emulate-rig")(live_commands.emulate_rig)
app.command("emulate-board")(live_commands.emulate_board)
app.command("unit-id")(live_commands.unit_id)

if __name__ == "__main__":
    app()
