"""`needlecue simulate`, `simulate-batch` and `check`: rig-log/1 batches written by the simulator, or
checked without running the pipeline."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer

from pipeline.cli.params import ParamsOption


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
    from pipeline.rig.check import check_batches

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
    from needlecue_runtime.vocab import one_line
    from pipeline.reporting.ledger import entry_text

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
