"""`needlecue rollback`, `ui` and `data-of`: the model registry by hand (a champion moved back, MLflow's
UI, the data behind a version)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from pipeline.exits import fail


def rollback(
    angle: Annotated[float, typer.Argument(help="insertion angle (deg) of the registered model")],
    to: Annotated[
        int | None, typer.Option("--to", help="version to make champion (default: the one it replaced)")
    ] = None,
) -> None:
    """Move `needle-force-<angle>@champion` back to an earlier version (exit 1: refused, including by a
    read-only store or something that is not MLflow; 2: offline). Nothing changes unless it succeeds."""
    from needlecue_runtime.registry.store import NotMlflow, ReadOnlyStore, RegistryUnreachable, model_name
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

    from needlecue_runtime.registry import mlflow_env, store
    from pipeline.registry.ui import SERVER_ENV, is_server, runs_link, server_command

    uri = store.tracking_uri()
    try:
        with mlflow_env.patience():
            client = store.connect(uri, must_exist=True)
            if is_server(uri):
                typer.echo(runs_link(client, uri))
                return
            link = runs_link(client, f"http://{host}:{port}")
    except store.RegistryUnreachable as e:
        raise fail(str(e), 2) from e
    # in a process group of its own, stopped whole: mlflow server runs uvicorn's workers under it
    server = subprocess.Popen(
        server_command(uri, host, port),
        stdout=sys.stderr,
        start_new_session=True,
        env={**os.environ, **SERVER_ENV},
    )
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

    from needlecue_runtime.registry.store import RegistryUnreachable
    from pipeline.registry.provenance import ProvenanceError, restore_lock

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
