"""What a larger LSTM batch would buy: training time against validation loss and test error.

The LSTM's training is the largest part of a cold `dvc repro` (issue 43). Each setting below
retrains the six angles' LSTMs exactly as the train stage does (`python -m pipeline.execution.run train lstm
...`, the pinned environment included), two at a time (the timings are per model, each on its own
core), from `make repro`'s data/processed and data/choices, with params.yaml's `lstm` section but
for the setting's overrides. One untimed training first warms the stages' preload server
(pipeline/execution/preload.py), so that no setting pays for starting it. Prints, per setting and angle: the
epochs run, the training loop's seconds (the stage's own "done ... in X s", without start-up, data
loading or writing), the best validation loss (what early stopping and any choice of settings may
look at), and the NRMSE (mean over axes, %) on the test split and on the external set's rows from
the training units (the same unit on a held-out cast); then the totals, all measured in this run.

Usage: `python benchmarks/bench_lstm_batch.py [--settings '{"batch_size": 256}' ...]`.
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

from needlecue_runtime.vocab import AXES
from pipeline.metrics.scores import nrmse_pct
from pipeline.modelling.predictor import load_predictor

DATA = Path("data/processed")
CHOICE = Path("data/choices/lstm.json")
SETTINGS = [
    "{}",
    '{"batch_size": 256}',
    '{"batch_size": 256, "lr": 0.007}',
    '{"batch_size": 512, "lr": 0.01}',
]


DONE = re.compile(r": done, .* in ([0-9.]+) s -> ")  # pipeline.modelling.train.train_folder's last line


def train(angle: str, params: Path, out: Path) -> float:
    """One angle's LSTM through the train stage's command; the seconds of its training loop."""
    cmd = [
        sys.executable,
        "-m",
        "pipeline.execution.run",
        "train",
        "lstm",
        str(DATA / angle),
        str(out / angle),
    ]
    run = [*cmd, "--choice", str(CHOICE), "--params", str(params)]
    done = subprocess.run(run, capture_output=True, text=True)
    found = DONE.search(done.stderr + done.stdout)
    if done.returncode or not found:
        raise RuntimeError(f"train lstm {angle} failed ({done.returncode}):\n{done.stderr[-2000:]}")
    return float(found.group(1))


def scores(angle: str, model_dir: Path) -> tuple[float, float]:
    """The test split's NRMSE and the external set's, on the rows of the units it was trained on."""
    model = load_predictor(model_dir)
    test = pd.read_parquet(DATA / angle / "test.parquet")
    external = pd.read_parquet(DATA / angle / "external.parquet")
    units = set(pd.read_parquet(DATA / angle / "train.parquet", columns=["unit_id"])["unit_id"])

    def nrmse(frame: pd.DataFrame) -> float:
        return float(np.mean(nrmse_pct(model.predict(frame), frame[list(AXES)].to_numpy())))

    return nrmse(test), nrmse(external[external["unit_id"].isin(units)])


def run_setting(overrides: dict, angles: list[str], work: Path) -> dict[str, float]:
    params = yaml.safe_load(Path("params.yaml").read_text())
    params["lstm"].update(overrides)
    work.mkdir(parents=True)
    (work / "params.yaml").write_text(yaml.safe_dump(params))
    started = time.perf_counter()
    with ThreadPoolExecutor(2) as pool:  # the machine's two cores, as `needlecue repro` trains
        loop_s = dict(
            zip(angles, pool.map(lambda a: train(a, work / "params.yaml", work), angles), strict=True)
        )
    wall = time.perf_counter() - started
    print(f"\nlstm {overrides or '(params.yaml)'}")
    print("angle  epochs  train s  s/epoch  best val loss  test NRMSE %  same unit, other cast %")
    totals = {"val": 0.0, "test": 0.0, "external": 0.0, "train_s": 0.0, "epochs": 0.0}
    for angle in sorted(angles, key=float):
        m = json.loads((work / angle / "train_metrics.json").read_text())
        test, ext = scores(angle, work / angle)
        print(
            f"{angle:>5}  {m['epochs_run']:6d}  {loop_s[angle]:7.1f}  {loop_s[angle] / m['epochs_run']:7.2f}"
            f"  {m['best_val_loss']:13.5f}  {test:12.3f}  {ext:22.3f}"
        )
        for key, value in zip(
            totals, (m["best_val_loss"], test, ext, loop_s[angle], m["epochs_run"]), strict=True
        ):
            totals[key] += value
    n, per_epoch = len(angles), totals["train_s"] / totals["epochs"]
    print(
        f"  all  {totals['epochs']:6.0f}  {totals['train_s']:7.1f}  {per_epoch:7.2f}"
        f"  {totals['val']:13.5f}  {totals['test'] / n:12.3f}  {totals['external'] / n:22.3f}"
        f"   (sum of val losses, mean NRMSE; {wall:.1f} s wall two at a time)"
    )
    return totals


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--settings", nargs="+", default=SETTINGS, help="JSON overrides of params.yaml's lstm"
    )
    parser.add_argument(
        "--angles", nargs="+", default=None, help="angles (default: every folder in data/processed)"
    )
    args = parser.parse_args()
    angles = args.angles or sorted(
        (p.name for p in DATA.iterdir() if (p / "train.parquet").is_file()), key=float
    )
    with tempfile.TemporaryDirectory(prefix="bench_lstm_") as tmp:
        train(min(angles, key=float), Path("params.yaml"), Path(tmp) / "warm-up")
        results = [
            (s, run_setting(json.loads(s), angles, Path(tmp) / str(i))) for i, s in enumerate(args.settings)
        ]
    base = results[0][1]
    print("\nagainst the first: training s, epochs, sum of val losses, mean NRMSE on test and the other cast")
    for setting, r in results[1:]:
        ratios = [r[k] / base[k] for k in ("train_s", "epochs", "val", "test", "external")]
        print(f"{setting}: " + ", ".join(f"{x:.2f}x" for x in ratios))


if __name__ == "__main__":
    main()
