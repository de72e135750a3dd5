"""The `--params` option of the `needlecue` commands and the settings they read from it."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer

ParamsOption = Annotated[Path, typer.Option("--params", help="params.yaml to read settings from")]


def section(model: Any, name: str, params: Path) -> Any:
    """One params.yaml section, or its defaults when there is no params file (a simulator's machine)."""
    from pipeline.config import load_section

    return load_section(model, name, params) if params.exists() else model()
