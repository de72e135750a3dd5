"""Our FNN against the peer a user would otherwise pick: scikit-learn's MLPRegressor.

Same per-angle splits (data/processed, from `make repro`), same inputs, same architecture
(inputs -> 20 -> 20 -> 3, tanh), same standardisation, early stopping on the validation split for
ours and MLPRegressor's own `early_stopping` for the peer (it holds out 10 % of the training rows).
Ours is fitted as the train stage fits it (`load_angle`: the training units' circuit; the choose
stage's inputs, data/choices/fnn.json); the peer reads those very inputs, computed by the pipeline's
own `features_of` from the volts (e.g. `rest_volts`: each channel less its rest reading), not the
raw volt columns.
Both are trained with SEEDS seeds (params.yaml's fnn.seed and the next ones): one seed's
difference between two nets this close is mostly the luck of the initialisation. Prints, per
angle, the external-set NRMSE (mean over axes, then over seeds) and the median training wall
time of each, then the medians over angles and the ratios peer/ours, all measured in this one run.
"""

from __future__ import annotations

import statistics
import time
import warnings
from pathlib import Path

import numpy as np
import pandas as pd

from needlecue_runtime.features import ModelInputs, spec_of
from needlecue_runtime.vocab import channels_of
from pipeline.config import load_section
from pipeline.dataset.splits import SplitFiles
from pipeline.metrics.scores import nrmse_pct
from pipeline.modelling.choice import load_choice
from pipeline.modelling.fit import fit
from pipeline.modelling.inputs import features_of
from pipeline.modelling.kinds.fnn import FNNParams
from pipeline.modelling.train import load_angle

DATA = Path("data/processed")
CHOICE = Path("data/choices/fnn.json")  # the choose stage's inputs for the FNN
TARGETS = ["fx", "fy", "fz"]
SEEDS = 3


def peer(train: pd.DataFrame, channels: list[str], spec: ModelInputs, p: FNNParams):
    from sklearn.neural_network import MLPRegressor
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import StandardScaler

    model = MLPRegressor(
        hidden_layer_sizes=p.hidden,
        activation=p.activation,
        learning_rate_init=p.lr,
        batch_size=p.batch_size,
        max_iter=p.max_epochs,
        n_iter_no_change=p.patience,
        early_stopping=True,
        random_state=p.seed,
    )
    y_scaler = StandardScaler().fit(train[TARGETS])
    pipe = make_pipeline(StandardScaler(), model)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        pipe.fit(features_of(train, channels, spec), y_scaler.transform(train[TARGETS]))
    return lambda frame: y_scaler.inverse_transform(pipe.predict(features_of(frame, channels, spec)))


def main() -> None:
    base = load_section(FNNParams, "fnn", Path("params.yaml"))
    decided = load_choice(CHOICE, "fnn") if base.inputs.kind == "auto" else None
    rows, read = [], set()
    files = SplitFiles(DATA)
    for angle in files.angles():  # the angle folders only (not calibration/)
        data = load_angle(DATA / angle)
        train, val, ext = data.train, data.val, files.frame(angle, "external")
        channels = channels_of(train)
        ref = ext[TARGETS].to_numpy()
        e_ours, e_peer, t_ours, t_peer = [], [], [], []
        for seed in range(base.seed, base.seed + SEEDS):
            p = base.model_copy(update={"seed": seed})
            t0 = time.perf_counter()
            designs = data.other_designs
            found = fit("fnn", p, train, val, front_end=data.circuit, other_designs=designs, decided=decided)
            t_ours.append(time.perf_counter() - t0)
            ours, spec = found.predictor, spec_of(found.checkpoint.get("inputs"))
            read.add(spec.kind)
            t0 = time.perf_counter()
            theirs = peer(train, channels, spec, p)
            t_peer.append(time.perf_counter() - t0)
            e_ours.append(float(np.mean(nrmse_pct(ours.predict(ext), ref))))
            e_peer.append(float(np.mean(nrmse_pct(theirs(ext), ref))))
        row = (
            angle,
            *map(statistics.mean, (e_ours, e_peer)),
            *map(statistics.median, (t_ours, t_peer)),
        )
        rows.append(row)
        print(
            f"{angle:>4}°  NRMSE ours {row[1]:5.2f} % (seeds {min(e_ours):.2f}-{max(e_ours):.2f})  "
            f"MLPRegressor {row[2]:5.2f} % ({min(e_peer):.2f}-{max(e_peer):.2f})   "
            f"train ours {row[3]:5.2f} s  MLPRegressor {row[4]:5.2f} s",
            flush=True,
        )
    med = [statistics.median(r[i] for r in rows) for i in range(1, 5)]
    print(f"both read the inputs {', '.join(sorted(read))}: the choose stage's (the peer's by features_of)")
    wins = sum(r[1] <= r[2] for r in rows)
    print(
        f"median NRMSE (mean of axes and of {SEEDS} seeds, external set): ours {med[0]:.3f} %, "
        f"MLPRegressor {med[1]:.3f} %; ours at least as accurate at {wins} of {len(rows)} angles"
    )
    print(f"median training time: ours {med[2]:.2f} s, MLPRegressor {med[3]:.2f} s")
    print(f"ratios MLPRegressor/ours: error {med[1] / med[0]:.3f}x, training time {med[3] / med[2]:.2f}x")


if __name__ == "__main__":
    main()
