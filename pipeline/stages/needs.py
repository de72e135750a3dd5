"""`needs` stage: how much data a lab needs, by subsampling its own data (issue 39).

Input: `DATA_DIR/<angle>/{train,external}.parquet`, `DATA_DIR/calibration/<angle>.parquet` and
`DATA_DIR/manifest.json` (the split stage's), and `CHOICES_DIR/<kind>.json` (the inputs the choose
stage gave each memoryless model kind: LS, the FNN). Output in `OUT_DIR`: `needs.json`
(`pipeline.needs.document`: force and cue figures against the training insertions per angle, the cues
against the calibration insertions per angle, the advice in words, what was not computed and why) and
`needs.png` (`pipeline.reporting.needs`). Small or odd data never stops the stage: what cannot be
computed is left out and said. It fails only on real errors: no training trials, bad params.

Usage: `python -m pipeline.execution.run needs DATA_DIR CHOICES_DIR OUT_DIR [--params params.yaml]`.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import typer

from pipeline.config import CuesParams, NeedsParams, load_section
from pipeline.logs import setup
from pipeline.modelling.kinds import TABLE
from pipeline.needs.advice import sentences
from pipeline.needs.curves import lab_data, needs_curves
from pipeline.needs.document import FILE, read_needs, stored_curves, write_needs
from pipeline.needs.force import force_models
from pipeline.reporting.needs import plot_needs

_log = logging.getLogger("pipeline.stages").info  # not __name__: a stage runs as __main__


def main(data_dir: Path, choices_dir: Path, out_dir: Path, params: Path = Path("params.yaml")) -> None:
    """Force and cue figures against the training and calibration insertions per angle, and advice."""
    setup("needs")
    started = time.perf_counter()
    try:
        if not params.is_file():
            raise FileNotFoundError(f"{params}: no such params file")
        p = load_section(NeedsParams, "needs", params)
        cues = load_section(CuesParams, "cues", params)
        # the memoryless kinds: a sequence kind's stand-in is the networks' with lags, and its model
        # refitted per subsample would cost minutes each
        kinds = [(k, load_section(kind.params, k, params)) for k, kind in TABLE.items() if not kind.sequence]
        data = lab_data(data_dir)
        models, notes = force_models(kinds, choices_dir, data.circuits, data.training_units)
        needs = needs_curves(data, p, cues, models, kinds[0][0], _log)
        needs["not_computed"] = notes + needs["not_computed"]
        curves = stored_curves(needs)  # the advice reads the curves as needs.json stores them
    except (FileNotFoundError, ValueError) as e:
        _log(f"error: {e}")
        raise typer.Exit(1) from e
    advice = sentences(curves)
    for n in curves.not_computed:
        _log(f"not computed: {n.what}: {n.why}")
    for line in advice:
        _log(f"advice: {line}")

    write_needs(out_dir / FILE, {**needs, "advice": advice})
    plot_needs(read_needs(out_dir / FILE), out_dir / "needs.png")
    _log(f"done in {time.perf_counter() - started:.1f} s -> {out_dir}")


if __name__ == "__main__":
    typer.run(main)
