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
    from pipeline import simulate as stage
    from pipeline.config import SimulateParams, load_section

    p = load_section(SimulateParams, "simulate", params) if params.exists() else SimulateParams()
    try:
        ids = stage.run(p.model_copy(update={"enabled": True}), out_dir)
    except FileExistsError as e:
        typer.echo(f"error: {e}", err=True)
        raise typer.Exit(2) from e
    typer.echo(f"wrote {len(ids)} batches to {out_dir}")


@app.command()
def check(
    raw_dirs: Annotated[list[Path], typer.Argument(help="raw folders, each holding batch folders")],
    params: ParamsOption = Path("params.yaml"),
) -> None:
    """Check rig-log/1 folders without running the pipeline; exit 1 if anything would be set aside."""
    from pipeline.config import IngestParams, load_section
    from pipeline.ingest import check_folders

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


if __name__ == "__main__":
    app()
