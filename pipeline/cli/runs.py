"""`needlecue repro` and `retrain`: the pipeline run by hand, on every core, or from a schedule."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Annotated

import typer

from pipeline.cli.params import ParamsOption
from pipeline.exits import fail


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
