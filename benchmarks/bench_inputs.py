"""Which model inputs transfer between estimator units: the input study behind `<model>.inputs`.

For each input kind of `pipeline.modelling.features` (raw volts, volts or conductance relative to the
trial's rest reading, conductance) and each model kind given (default: ls and fnn; lstm takes
~40 s per angle), trains one model per angle on the processed training splits (`make repro` first;
DATA_DIR defaults to data/processed) with params.yaml's settings and only `inputs.kind` changed, and
prints the external NRMSE (mean over axes, then angles) on the training units' held-out casts
("same unit") and on new units' held-out casts without calibration ("new unit"), with their ratio.

Usage: `python -m benchmarks.bench_inputs [DATA_DIR] [--kinds ls,fnn]`.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd

from pipeline.config import PARAMS_MODELS, load_section
from pipeline.dataset.splits import SplitFiles, unit_roles
from pipeline.metrics.scores import nrmse_pct
from pipeline.modelling.features import KINDS as INPUT_KINDS
from pipeline.modelling.fit import fit

AXES = ["fx", "fy", "fz"]


def score(model, frame: pd.DataFrame) -> float:
    if frame.empty:
        return float("nan")
    return float(np.mean(nrmse_pct(model.predict(frame.drop(columns=AXES)), frame[AXES].to_numpy())))


def main() -> None:
    args = [a for a in sys.argv[1:] if not a.startswith("--")]
    data = Path(args[0]) if args else Path("data/processed")
    kinds = ["ls", "fnn"]
    for a in sys.argv[1:]:
        if a.startswith("--kinds="):
            kinds = a.split("=", 1)[1].split(",")
    files, roles = SplitFiles(data), unit_roles(data)
    print(f"{'model':<6}{'inputs':<18}{'same unit %':>12}{'new unit %':>12}{'ratio':>8}{'train s':>9}")
    for kind in kinds:
        base = load_section(PARAMS_MODELS[kind], kind, Path("params.yaml"))
        for inputs in INPUT_KINDS:
            p = base.model_copy(update={"inputs": base.inputs.model_copy(update={"kind": inputs})})
            same, new, seconds = [], [], 0.0
            for angle in files.angles():
                started = time.perf_counter()
                model = fit(kind, p, files.frame(angle, "train"), files.frame(angle, "val")).predictor
                seconds += time.perf_counter() - started
                ext = files.frame(angle, "external")
                trained = ext["unit_id"].map(lambda u: roles.get(u) == "training")
                same.append(score(model, ext[trained]))
                new.append(score(model, ext[~trained]))
            s, n = float(np.nanmean(same)), float(np.nanmean(new))
            print(f"{kind:<6}{inputs:<18}{s:>12.2f}{n:>12.2f}{n / s:>8.2f}{seconds:>9.1f}", flush=True)


if __name__ == "__main__":
    main()
