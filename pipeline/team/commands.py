"""The team commands of `needlecue` (`needlecue team ...`; `pipeline.cli` adds them): start, stop and
look at the team stack, hand out its credentials, and publish champions to the simulators' bucket
(docs/team.md). Heavy imports stay inside the functions, so `needlecue --help` stays quick."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer

from pipeline.exits import fail

team = typer.Typer(
    no_args_is_help=True,
    help="The team stack on this machine: PostgreSQL, S3 (SeaweedFS), MLflow with basic auth and the "
    "publisher of champions to simulators (docs/team.md).",
)
TeamDir = Annotated[
    Path | None,
    typer.Option(
        "--dir",
        help="the stack's state folder (default $NEEDLECUE_TEAM_DIR or ~/.local/state/needlecue/team)",
    ),
]


def _stack(folder: Path | None) -> Any:
    from pipeline.team.stack import Stack

    return Stack(folder)


@team.command("start")
def team_start(
    folder: TeamDir = None,
    port: Annotated[
        int, typer.Option(help="base port: MLflow on it, S3 on +1, PostgreSQL on +2 (first start only)")
    ] = 5480,
    host: Annotated[str, typer.Option(help="address every server binds to (first start only)")] = "127.0.0.1",
) -> None:
    """Start PostgreSQL, SeaweedFS, the MLflow server and the publisher (generating credentials and the
    lab's signing key on the first start), and print how to use them."""
    from pipeline.team.servers.base import StackError

    stack = _stack(folder)
    try:
        if stack.init(base_port=port, host=host):
            typer.echo(f"new team stack in {stack.dir} (credentials in {stack.file}, mode 0600)")
        stack.start(progress=typer.echo)
    except (StackError, ValueError) as e:
        raise fail(str(e)) from e
    typer.echo(f"MLflow: {stack.tracking_uri} (users admin, lab, simulator)   S3: {stack.s3_endpoint}")
    typer.echo(f"simulators read {stack.published_url} (published on every alias change, signed)")
    typer.echo(f"as the lab:   set -a; . {stack.dir / 'lab.env'}; set +a")
    typer.echo(f"a simulator:  set -a; . {stack.dir / 'simulator.env'}; set +a")


@team.command("stop")
def team_stop(
    folder: TeamDir = None,
    purge: Annotated[
        bool, typer.Option(help="also delete everything the stack stored, credentials included")
    ] = False,
) -> None:
    """Stop the stack's servers (their data stays unless --purge)."""
    from pipeline.team.servers.base import StackError

    stack = _stack(folder)
    try:
        stopped = stack.stop(purge=purge)
    except StackError as e:
        raise fail(str(e)) from e
    typer.echo(
        f"stopped: {', '.join(stopped) or 'nothing was running'}"
        + (f"; deleted {stack.dir}" if purge else "")
    )


@team.command("status")
def team_status(folder: TeamDir = None) -> None:
    """Each server: running or not, address, log; and the S3 store's free disk (exit 1 unless all of them
    run and it can write)."""
    from pipeline.team.servers.base import StackError

    try:
        stack = _stack(folder)
        found = stack.status()
        space = stack.disk_space()
    except StackError as e:
        raise fail(str(e)) from e
    for server, s in found.items():
        state = f"running (pid {s['pid']})" if s["running"] else "stopped"
        typer.echo(f"{server:9} {state:22} {s['address']:28} log {s['log']}")
    typer.echo(("error: " if space.full else "warning: " if space.low else "") + space.describe())
    if space.full or not all(s["running"] for s in found.values()):
        raise typer.Exit(1)


@team.command("units")
def team_units(
    folder: TeamDir = None,
    out: Annotated[Path, typer.Option(help="where to write the unit files")] = Path("deploy/systemd"),
) -> None:
    """Write a systemd unit per server (and needlecue-team.target) that runs the stack as `team start`
    does, restarted on failure: the registry outlives a terminal and a reboot (docs/team.md)."""
    from pipeline.team.servers.base import StackError
    from pipeline.team.services import TARGET, write_units

    stack = _stack(folder)
    try:
        stack.settings  # noqa: B018 (a stack that was never started is an error here, not a KeyError)
        if not (stack.pg_dir / "PG_VERSION").is_file():
            raise StackError(
                f"PostgreSQL has no data in {stack.pg_dir}: run `needlecue team start` once first"
            )
        written = write_units(stack, out)
    except (StackError, OSError) as e:
        raise fail(str(e)) from e
    for path in written:
        typer.echo(f"wrote {path}")
    typer.echo(
        f"install: needlecue team stop; sudo cp {out}/* /etc/systemd/system/ && sudo systemctl daemon-reload"
    )
    typer.echo(f"         sudo systemctl enable --now {TARGET}")


@team.command("env")
def team_env(
    role: Annotated[str, typer.Argument(help="admin, lab or simulator")],
    folder: TeamDir = None,
) -> None:
    """Print `export` lines for one role: `eval "$(needlecue team env lab)"`."""
    import shlex

    from pipeline.team.servers.base import StackError

    try:
        env = _stack(folder).role_env(role)
    except (StackError, ValueError) as e:
        raise fail(str(e)) from e
    for key, value in env.items():
        typer.echo(f"export {key}={shlex.quote(value)}")


@team.command("add-user")
def team_add_user(
    username: Annotated[str, typer.Argument(help="the new user's name")],
    role: Annotated[str, typer.Option(help="lab or simulator")] = "simulator",
    folder: TeamDir = None,
) -> None:
    """Create a user with a role (as the admin) and print its generated password once."""
    from pipeline.team import access

    try:
        password = access.add_user(_stack(folder), username, role)
    except Exception as e:  # the auth server's refusal, an unknown role, a stopped stack
        raise fail(str(e)) from e
    typer.echo(f"{username} ({role}): password {password}")


@team.command("webhook")
def team_webhook(
    url: Annotated[str, typer.Argument(help="a simulator's listener, e.g. http://10.0.0.7:8765/mlflow")],
    folder: TeamDir = None,
) -> None:
    """Have MLflow call URL on every alias change (HMAC-signed with the stack's webhook secret)."""
    from pipeline.team import access

    try:
        hook = access.add_webhook(_stack(folder), url)
    except Exception as e:
        raise fail(str(e)) from e
    typer.echo(f"webhook {hook}: alias changes -> {url}")


@team.command("publish")
def team_publish(
    check: Annotated[
        bool, typer.Option("--check", help="only say what is out of date (exit 1 if anything is)")
    ] = False,
    model: Annotated[
        list[str] | None,
        typer.Option("--model", help="only this registered model (repeat for more); default: all"),
    ] = None,
    folder: TeamDir = None,
) -> None:
    """Publish every alias of the registry to the bucket simulators read (signed manifests, objects by
    hash); the stack's publisher does it on every alias change by itself."""
    from pipeline.team import publish

    stack = _stack(folder)
    try:
        with stack.as_lab():
            target = publish.Target.of(stack)
            changes = publish.publish(stack.tracking_uri, target, names=model, check_only=check)
    except Exception as e:  # a stopped stack, refused credentials
        raise fail(f"publish: {type(e).__name__}: {e}") from e
    for change in changes:
        said = "out of date" if check else "cannot publish" if change.action == "refused" else "published"
        typer.echo(f"{said}: {change}")
    if not changes:
        typer.echo(f"{stack.published_url}: up to date with {stack.tracking_uri}")
    if (check and changes) or any(c.action == "refused" for c in changes):
        raise typer.Exit(1)
