"""Does a unit's calibration help the cue estimator? Checked on the training units alone.

For each training unit in turn (`make repro` first; DATA_DIR defaults to data/processed): fits the
angle estimator and the cue packs on the other training units' training trials (params.yaml's
`cues`), takes the held-out unit's first insertion at each angle as its calibration, and scores its
other insertions (its training trials and its external cast) with the combined cue, uncalibrated
(read as the average unit) and calibrated. Prints balanced accuracy within `cues.cue_within_s`.
The reference force stands in for the model ("ls" in the params copy): the combined cue reads it
only for the force check.

Usage: `python -m benchmarks.bench_cue_units [DATA_DIR]`.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd

from needlecue_runtime.vocab import AXES, channels_of
from pipeline.config import CuesParams, load_section
from pipeline.cues.estimator import fit_angle_estimator
from pipeline.cues.packs import build_cue_pack
from pipeline.cues.score import evaluate_cues
from pipeline.cues.unit_evidence import evidence_of, trial_features
from pipeline.dataset.splits import SplitFiles, unit_roles


def _split(frames: dict[float, pd.DataFrame], unit: str) -> tuple[dict, dict, dict]:
    """(others' frames, the unit's calibration frames, the unit's other frames)."""
    others = {a: f[f["unit_id"] != unit].reset_index(drop=True) for a, f in frames.items()}
    calib, rest = {}, {}
    for a, f in frames.items():
        mine = f[f["unit_id"] == unit]
        first = sorted(zip(mine["batch_id"], mine["trial_id"], strict=True))[0]
        is_first = (mine["batch_id"] == first[0]) & (mine["trial_id"] == first[1])
        calib[a] = mine[is_first].reset_index(drop=True)
        rest[a] = mine[~is_first].reset_index(drop=True)
    return others, calib, rest


def main() -> None:
    data = Path(sys.argv[1]) if len(sys.argv) > 1 else Path("data/processed")
    params = load_section(CuesParams, "cues", Path("params.yaml")).model_copy(update={"kinds": ("ls",)})
    files = SplitFiles(data)
    train, external = files.by_angle("train"), files.by_angle("external")
    units = sorted(u for u, role in unit_roles(data).items() if role == "training")
    channels = channels_of(next(iter(train.values())))
    print(f"{'held-out unit':<16}{'trials':>8}{'uncalibrated %':>16}{'calibrated %':>14}{'s':>7}")
    rows = []
    for unit in units:
        started = time.perf_counter()
        others, calib, test = _split(train, unit)
        for a, f in external.items():
            test[a] = pd.concat([test[a], f[f["unit_id"] == unit]], ignore_index=True)
        estimator = fit_angle_estimator(others, params)
        packs = {a: build_cue_pack(others, a, params, None, angle_estimator=estimator) for a in others}
        levels = estimator["levels"]  # the unit's evidence at the estimator's loading levels
        trials = trial_features(calib, channels, params, levels=levels)[0]
        evidence = evidence_of(trials, len(channels)).get(unit, {})
        scores = []
        for known in ({}, {unit: evidence}):
            ev = evaluate_cues(
                test,
                params,
                packs,
                lambda _kind, _preset, a, test=test: test[a][list(AXES)].to_numpy(),
                log=lambda _m: None,
                units=known,
            )
            scores.append(100 * ev["results"]["ls"]["combined"]["balanced_within_s"])
        n = sum(f.groupby(["batch_id", "trial_id"]).ngroups for f in test.values())
        rows.append(scores)
        seconds = time.perf_counter() - started
        print(f"{unit:<16}{n:>8}{scores[0]:>16.1f}{scores[1]:>14.1f}{seconds:>7.0f}", flush=True)
    mean = np.mean(rows, axis=0)
    print(f"{'mean':<16}{'':>8}{mean[0]:>16.1f}{mean[1]:>14.1f}")


if __name__ == "__main__":
    main()
