"""Which model inputs transfer between estimator units: the input study behind `<model>.inputs`.

For each input kind of `needlecue_runtime.features` (raw volts, volts or conductance relative to the
trial's rest reading, conductance) and each model kind given (default: ls and fnn; lstm takes
~40 s per angle), trains one model per angle on the processed training splits (`make repro` first;
DATA_DIR defaults to data/processed) with params.yaml's settings and only `inputs.kind` changed, and
prints the external NRMSE (mean over axes, then angles) on the training units' held-out casts
("same unit") and on new units' held-out casts without calibration ("new unit"), with their ratio.
Every model reads through the circuit its training units declare, and a unit that declares another
is read through its own, as in the pipeline; the conductance kinds are skipped where no circuit is
declared. The pipeline's own choice (`inputs.kind: auto`: one kind for all angles, as the choose
stage makes it) is the last row of each model kind.

Usage: `python -m benchmarks.bench_inputs [DATA_DIR] [--kinds=ls,fnn] [--params=params.yaml]`.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd

from needlecue_runtime.features import INPUT_KINDS, NEEDS_CIRCUIT
from needlecue_runtime.frontend import Circuit
from needlecue_runtime.vocab import angle_name
from pipeline.config import load_section
from pipeline.dataset.splits import SplitFiles, unit_roles
from pipeline.metrics.scores import nrmse_pct
from pipeline.modelling.fit import fit
from pipeline.modelling.kinds import kind_of
from pipeline.modelling.split_predictions import predict_model
from pipeline.modelling.train import choose_folders, load_angle

AXES = ["fx", "fy", "fz"]
AUTO = "auto"  # the pipeline's own choice, by validation


def score(model, frame: pd.DataFrame, circuits: dict[str, Circuit | None]) -> float:
    """Mean NRMSE over axes of `model` on `frame`, predicted as the predict stage does (each unit's
    rows through its own circuit where it declares another)."""
    if frame.empty:
        return float("nan")
    block = {("bench", "external"): frame.reset_index(drop=True)}
    table = predict_model(model, block, "bench", lambda _m: None, None, circuits)[0]
    pred = np.column_stack([table[a].to_numpy() for a in AXES])
    return float(np.mean(nrmse_pct(pred, frame[AXES].to_numpy())))


def main() -> None:
    args = [a for a in sys.argv[1:] if not a.startswith("--")]
    data = Path(args[0]) if args else Path("data/processed")
    kinds, params = ["ls", "fnn"], Path("params.yaml")
    for a in sys.argv[1:]:
        if a.startswith("--kinds="):
            kinds = a.split("=", 1)[1].split(",")
        if a.startswith("--params="):
            params = Path(a.split("=", 1)[1])
    files, roles = SplitFiles(data), unit_roles(data)
    circuits = files.front_ends()
    print(f"{'model':<6}{'inputs':<18}{'same unit %':>12}{'new unit %':>12}{'ratio':>8}{'train s':>9}")
    for kind in kinds:
        base = load_section(kind_of(kind).params, kind, params)
        for inputs in [*INPUT_KINDS, AUTO]:
            p = base.model_copy(update={"inputs": base.inputs.model_copy(update={"kind": inputs})})
            same, new, seconds = [], [], 0.0
            started = time.perf_counter()
            quiet = lambda _m: None  # noqa: E731
            choice = choose_folders(kind, p, data, files.angles(), quiet) if inputs == AUTO else None
            seconds += time.perf_counter() - started
            for angle in files.angles():
                # as the train stage reads it (pipeline.modelling.train)
                found = load_angle(data / angle_name(angle))
                if inputs in NEEDS_CIRCUIT and found.circuit is None:
                    break
                started = time.perf_counter()
                model = fit(
                    kind,
                    p,
                    found.train,
                    found.val,
                    front_end=found.circuit,
                    other_designs=found.other_designs,
                    decided=choice,
                ).predictor
                seconds += time.perf_counter() - started
                ext = files.frame(angle, "external")
                trained = ext["unit_id"].map(lambda u: roles.get(u) == "training")
                same.append(score(model, ext[trained], circuits))
                new.append(score(model, ext[~trained], circuits))
            else:
                s, n = float(np.nanmean(same)), float(np.nanmean(new))
                print(f"{kind:<6}{inputs:<18}{s:>12.2f}{n:>12.2f}{n / s:>8.2f}{seconds:>9.1f}", flush=True)
                continue
            print(f"{kind:<6}{inputs:<18}  (no circuit declared: skipped)", flush=True)


if __name__ == "__main__":
    main()
