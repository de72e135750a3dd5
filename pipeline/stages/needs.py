"""`needs` stage: how much data a lab needs, by subsampling its own data (issue 39).

Input: `DATA_DIR/<angle>/{train,external}.parquet`, `DATA_DIR/calibration/<angle>.parquet` and
`DATA_DIR/manifest.json` (the split stage's), and `CHOICES_DIR/{ls,fnn}.json` (the inputs the
choose stage gave LS and the FNN). Output in `OUT_DIR`: `needs.json` (format "needlecue-needs/1":
force and cue figures against the training insertions per angle, the cues against the calibration
insertions per angle, the advice in words, what was not computed and why; `pipeline.needs`) and
`needs.png` (`pipeline.reporting.needs`). Small or odd data never stops the stage: what cannot be
computed is left out and said. It fails only on real errors: no training trials, bad params.

Usage: `python -m pipeline.execution.run needs DATA_DIR CHOICES_DIR OUT_DIR [--params params.yaml]`.
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

import typer

from pipeline.config import CuesParams, FNNParams, LSParams, NeedsParams, load_section
from pipeline.logs import setup
from pipeline.needs.advice import sentences
from pipeline.needs.curves import lab_data, needs_curves
from pipeline.needs.force import force_models
from pipeline.reporting.needs import plot_needs
from pipeline.vocab import dump_json

_log = logging.getLogger("pipeline.stages").info  # not __name__: a stage runs as __main__
DIGITS = 6  # needs.json precision: fractions to 0.0001 %, like evaluation.json


def main(data_dir: Path, choices_dir: Path, out_dir: Path, params: Path = Path("params.yaml")) -> None:
    """Force and cue figures against the training and calibration insertions per angle, and advice."""
    setup("needs")
    started = time.perf_counter()
    try:
        if not params.is_file():
            raise FileNotFoundError(f"{params}: no such params file")
        p = load_section(NeedsParams, "needs", params)
        cues = load_section(CuesParams, "cues", params)
        ls, fnn = load_section(LSParams, "ls", params), load_section(FNNParams, "fnn", params)
        data = lab_data(data_dir)
        models, notes = force_models(ls, fnn, choices_dir, data.circuits, data.training_units)
        needs = needs_curves(data, p, cues, models, _log)
    except (FileNotFoundError, ValueError) as e:
        _log(f"error: {e}")
        raise typer.Exit(1) from e
    needs["not_computed"] = notes + needs["not_computed"]
    needs = json.loads(dump_json(needs, DIGITS))  # the advice reads the curves as needs.json stores them
    needs["advice"] = sentences(needs)
    for n in needs["not_computed"]:
        _log(f"not computed: {n['what']}: {n['why']}")
    for line in needs["advice"]:
        _log(f"advice: {line}")

    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "needs.json").write_text(dump_json(needs, DIGITS))
    plot_needs(needs, out_dir / "needs.png")
    _log(f"done in {time.perf_counter() - started:.1f} s -> {out_dir}")


if __name__ == "__main__":
    typer.run(main)
