"""`simulate` stage: write the built-in simulator's rig-log/1 batches (`pipeline.sim.rig`) as
configured in params.yaml's `simulate` section, standing in for a lab.

Usage: `python -m pipeline.execution.run simulate OUT_DIR [--params params.yaml]`. OUT_DIR must be new,
empty or written by the simulator before (it is then cleared).
"""

from __future__ import annotations

import logging
from pathlib import Path

import typer

from pipeline.config import SimulateParams, load_section
from pipeline.logs import setup
from pipeline.sim.rig import run

_log = logging.getLogger("pipeline.stages").info  # not __name__: a stage runs as __main__


def main(out_dir: Path, params: Path = Path("params.yaml")) -> None:
    """Write the simulated rig-log/1 batches configured in params.yaml's `simulate` section."""
    setup()
    try:
        run(load_section(SimulateParams, "simulate", params), out_dir, log=_log)
    except (OSError, ValueError) as e:  # a foreign OUT_DIR, bad params: one clear line, not a traceback
        _log(f"simulate: error: {e}")
        raise typer.Exit(1) from e


if __name__ == "__main__":
    typer.run(main)
