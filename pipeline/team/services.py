"""The team stack as systemd services: one unit per server, written from the same settings and the
same commands `needlecue team start` runs (`Stack.launch`), so a lab's registry outlives a terminal
and a reboot. `needlecue team units` writes them.

Each unit runs its server in the foreground and restarts it when it fails. The secrets a server
needs (database password, S3 keys, MLflow's secrets) are in an environment file beside the stack's
state (mode 0600), never in the unit. `needlecue-team.target` starts the four in order: PostgreSQL
and S3 first, then MLflow, then the publisher.
"""

from __future__ import annotations

import os
import pwd
import shlex
from pathlib import Path

from pipeline.team.servers.base import Launch, write_private
from pipeline.team.stack import SERVERS, Stack

TARGET = "needlecue-team.target"
DESCRIPTIONS = {
    "postgres": "PostgreSQL: MLflow's tracking, registry and auth stores",
    "s3": "SeaweedFS: S3 store of MLflow's artifacts, the DVC remote and the published bucket",
    "mlflow": "MLflow tracking server with basic auth",
    "publisher": "needlecue publisher: signs and publishes champions on every alias change",
}
NEEDS = {"postgres": (), "s3": (), "mlflow": ("postgres", "s3"), "publisher": ("mlflow", "s3")}
STOP_S = {"postgres": 90, "s3": 30, "mlflow": 30, "publisher": 15}


def unit_name(server: str) -> str:
    return f"needlecue-team-{server}.service"


def env_file(stack: Stack, server: str) -> Path:
    return stack.dir / "systemd" / f"{server}.env"


def _value(v: str) -> str:
    """A value as systemd's EnvironmentFile reads it: quoted, with its own escapes."""
    return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'


def unit_text(stack: Stack, server: str, launch: Launch) -> str:
    """The `.service` unit of one server."""
    after = " ".join(unit_name(s) for s in NEEDS[server])
    lines = [
        "# Written by `needlecue team units` from the team stack in " + str(stack.dir) + ": write it again",
        "# after changing the stack's settings, rather than editing it.",
        "[Unit]",
        f"Description=needlecue team stack: {DESCRIPTIONS[server]}",
        "After=network-online.target" + (f" {after}" if after else ""),
        "Wants=network-online.target",
        *([f"Requires={after}"] if after else []),
        f"PartOf={TARGET}",
        "",
        "[Service]",
        "Type=simple",
        # always named: a system unit runs as root otherwise, and the stack belongs to who made it
        f"User={launch.user or pwd.getpwuid(os.geteuid()).pw_name}",
        f"WorkingDirectory={launch.cwd}",
        *([f"EnvironmentFile={env_file(stack, server)}"] if launch.env else []),
        f"ExecStart={shlex.join(launch.cmd)}",
        "Restart=on-failure",
        "RestartSec=5",
        f"TimeoutStopSec={STOP_S[server]}",
        "KillMode=mixed",
        *(["KillSignal=SIGINT"] if server == "postgres" else []),  # its fast shutdown
        "",
        "[Install]",
        f"WantedBy={TARGET}",
        "",
    ]
    return "\n".join(lines)


def target_text() -> str:
    wants = " ".join(unit_name(s) for s in SERVERS)
    return "\n".join(
        [
            "# Written by `needlecue team units`: the team stack's four servers, started in order.",
            "[Unit]",
            "Description=needlecue team stack (PostgreSQL, S3, MLflow, publisher)",
            f"Wants={wants}",
            f"After={wants}",
            "",
            "[Install]",
            "WantedBy=multi-user.target",
            "",
        ]
    )


def write_units(stack: Stack, out_dir: Path) -> list[Path]:
    """Write the four units and the target into `out_dir`, and each server's environment file
    (secrets, mode 0600) into the stack's folder; returns the unit files written."""
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for server in SERVERS:
        launch = stack.launch(server)
        if launch.env:
            path = env_file(stack, server)
            path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
            write_private(path, "".join(f"{k}={_value(v)}\n" for k, v in sorted(launch.env.items())))
        unit = out_dir / unit_name(server)
        unit.write_text(unit_text(stack, server, launch))
        written.append(unit)
    target = out_dir / TARGET
    target.write_text(target_text())
    return [*written, target]
