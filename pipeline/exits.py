"""How a `needlecue` command ends on an error: the message on stderr, then its exit code."""

from __future__ import annotations

import typer


def fail(message: str, code: int = 1) -> typer.Exit:
    """Print `error: <message>` on stderr and give the Exit to raise (1: bad input or state; 2: a
    folder, server or registry that is not there)."""
    typer.echo(f"error: {message}", err=True)
    return typer.Exit(code)
