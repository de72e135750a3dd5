"""`choose` stage: one model kind's inputs, chosen once for all its angles (`inputs.kind: auto`).

Input: `DATA_ROOT/<angle>/` (the split stage's folders) for each of `train.angles`. Output: `OUT_FILE`
(`pipeline.modelling.choice.save_choice`): the kind chosen by the mean score over the angles, the
folds and the stand-in (the scores are logged; each train stage records its own angle's); the train
stages read it. With a kind pinned in params nothing is scored and the file says so.

Usage: `python -m pipeline.execution.run choose {ls|fnn|lstm} DATA_ROOT OUT_FILE [--params params.yaml]`.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import cast

import typer

from pipeline.config import TrainParams, load_section
from pipeline.logs import setup
from pipeline.modelling.choice import save_choice
from pipeline.modelling.kinds import TABLE
from pipeline.modelling.kinds.base import KindParams
from pipeline.modelling.train import choose_folders

_log = logging.getLogger("pipeline.stages").info  # not __name__: a stage runs as __main__


def main(kind: str, data_root: Path, out_file: Path, params: Path = Path("params.yaml")) -> None:
    """Choose one model kind's inputs on all the trained angles' processed folders."""
    setup("choose")
    if kind not in TABLE:
        raise typer.BadParameter(f"unknown model kind {kind!r}; expected one of {', '.join(TABLE)}")
    try:
        section = cast("KindParams", load_section(TABLE[kind].params, kind, params))
        if section.inputs.kind != "auto":
            _log(f"{kind}: inputs pinned in params ({section.inputs.kind}), nothing to choose")
            save_choice(out_file, kind, None, pinned=section.inputs.kind)
            return
        angles = load_section(TrainParams, "train", params).angles
        save_choice(out_file, kind, choose_folders(kind, section, data_root, angles, _log))
    except (FileNotFoundError, ValueError) as e:  # bad input: one clear line, not a traceback
        _log(f"error: {e}")
        raise typer.Exit(1) from e


if __name__ == "__main__":
    typer.run(main)
