"""`train` stage: one model of a kind (ls, fnn or lstm) for one angle's processed data.

Input: `DATA_DIR/train.parquet` and `DATA_DIR/val.parquet` (the split stage's; val may be empty,
then the networks train all `max_epochs` without early stopping), and `DATA_DIR/front_ends.json`
(the circuit the training units declare). With `inputs.kind: auto` the inputs are those of the
choose stage's `--choice` file (all angles'; without it, chosen on this angle alone). Output in `OUT_DIR`:
`model.pt` (see `pipeline.modelling.checkpoint`), `train_metrics.json`, `history.csv`.
Only the kind's own params section is read, so editing `fnn` never retrains `lstm`.

Usage: `python -m pipeline.execution.run train {ls|fnn|lstm} DATA_DIR OUT_DIR [--choice FILE]
[--params params.yaml]`.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import cast

import typer

from pipeline.config import load_section
from pipeline.logs import setup
from pipeline.modelling.choice import load_choice
from pipeline.modelling.kinds import TABLE
from pipeline.modelling.kinds.base import KindParams
from pipeline.modelling.train import train_folder

_log = logging.getLogger("pipeline.stages").info  # not __name__: a stage runs as __main__


def main(
    kind: str, data_dir: Path, out_dir: Path, choice: Path | None = None, params: Path = Path("params.yaml")
) -> None:
    """Train one model of `kind` (ls, fnn or lstm) on one angle's processed data folder."""
    setup("train")
    if kind not in TABLE:
        raise typer.BadParameter(f"unknown model kind {kind!r}; expected one of {', '.join(TABLE)}")
    try:
        section = cast("KindParams", load_section(TABLE[kind].params, kind, params))
        chosen = load_choice(choice, kind) if choice is not None and section.inputs.kind == "auto" else None
        train_folder(kind, section, data_dir, out_dir, _log, chosen)
    except (FileNotFoundError, ValueError) as e:  # bad input: one clear line, not a traceback
        _log(f"error: {e}")
        raise typer.Exit(1) from e


if __name__ == "__main__":
    typer.run(main)
