"""How sure the angle estimator must be before a cue is shown: the temperature that calibrates its
posterior, and the P(deviation class) a cue needs, chosen on cross-validated trials so that the share of
insertion frames showing a wrong cue stays within `max_wrong` (per reading of a unit).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from needlecue_runtime.cues.pack import VERDICTS, cue_for_deviation, sig
from pipeline.config import CuesParams


def softmax(z: np.ndarray) -> np.ndarray:
    z = z - z.max(axis=-1, keepdims=True)
    e = np.exp(z)
    return e / e.sum(axis=-1, keepdims=True)


def fit_temperature(logits: np.ndarray, y: np.ndarray) -> float:
    """The temperature minimising the cross-validated negative log-likelihood (grid, deterministic)."""
    if np.ptp(logits, axis=1).max(initial=0.0) == 0.0:
        return 1.0  # a flat posterior says nothing of the temperature
    best_t, best_nll = 1.0, math.inf
    for temp in np.geomspace(0.2, 20.0, 81):
        p = softmax(logits / temp)
        nll = -float(np.mean(np.log(np.clip(p[np.arange(len(y)), y], 1e-300, None))))
        if nll < best_nll - 1e-12:
            best_t, best_nll = float(temp), nll
    return best_t


CONFIDENCE_GRID = tuple(round(0.5 + 0.01 * i, 2) for i in range(50))  # 0.50 .. 0.99


def min_confidence_of(
    cv_probs: Sequence[tuple[int, int, np.ndarray]],
    trials: Sequence[Any],
    angles: Sequence[float],
    n_stages: int,
    params: CuesParams,
) -> dict[str, Any]:
    """The P(deviation class) a cue needs, and what it gives on the cross-validated trials: with
    `min_confidence: auto`, the least value of CONFIDENCE_GRID at and above which the share of
    insertion frames showing a wrong cue stays at or under `max_wrong`, every trained angle taken as
    the preset in turn. Each trial's stage counts for the insertion frames it is the latest stage
    (`TrialFeatures.frames`; stages past the last fitted one count for it, as the tracker reads them)."""
    pinned = params.min_confidence != "auto"
    grid = np.asarray([params.min_confidence] if pinned else CONFIDENCE_GRID, dtype=np.float64)
    wrong, shown, total = np.zeros(len(grid)), np.zeros(len(grid)), 0.0
    for preset in angles:
        dev = np.array(
            [
                VERDICTS.index(cue_for_deviation(a - preset, params.continue_below_deg, params.stop_from_deg))
                for a in angles
            ]
        )
        for i, j, p in cv_probs:
            frames = trials[i].frames
            w = float(sum(frames[j:])) if j == n_stages - 1 else float(frames[j] if j < len(frames) else 0)
            if not w:
                continue
            pdev = np.bincount(dev, weights=p, minlength=len(VERDICTS))
            best = int(np.argmax(pdev))
            on = pdev[best] >= grid - 1e-12
            shown += w * on
            wrong += w * on * (best != dev[label_of(angles, trials[i].angle)])
            total += w
    rate = wrong / total if total else np.zeros(len(grid))
    if pinned:
        k, how = 0, "pinned in params"
    else:
        fine = rate <= params.max_wrong + 1e-12
        holds = np.flatnonzero(np.logical_and.accumulate(fine[::-1])[::-1])  # fine here and above
        k = int(holds[0]) if len(holds) else len(grid) - 1
        how = f"auto: cross-validated wrong-cue frames <= {params.max_wrong:g}"
        if not len(holds):
            how += " not reached on the grid; its top value"
    return {
        "min_confidence": sig(grid[k], 4),
        "chosen_by": how,
        "cv_wrong_frames": sig(rate[k] if total else 0.0, 4),
        "cv_coverage": sig(shown[k] / total if total else 0.0, 4),
        "cv_frames": int(total),
    }


def reading_confidence(
    cv_probs: Sequence[tuple[int, int, np.ndarray]],
    trials: Sequence[Any],
    angles: Sequence[float],
    n_stages: int,
    params: CuesParams,
    training: float,
) -> dict[str, Any]:
    """The P a cue needs for a unit read another way than as a training unit (a unit left out, read
    calibrated or not: `cv_probs`), and what it gives in cross-validation: the training units' value
    `training`, its own temperature putting it on their footing. Where that footing does not hold,
    i.e. the unit left out shows more wrong frames than `max_wrong` at `training`, and the confidence is
    "auto": the least value that holds its own budget, as `min_confidence_of` chooses it, where that is
    above `training`. Measured on `power-law` with three calibration insertions per angle, the training
    units' value let 3.7 % of a new unit's insertions end on a wrong cue (docs/units.md)."""
    at = params.model_copy(update={"min_confidence": training})
    c = {
        **min_confidence_of(cv_probs, trials, angles, n_stages, at),
        "chosen_by": "the training units' (its own temperature puts it on their footing)",
    }
    if params.min_confidence != "auto" or c["cv_wrong_frames"] <= params.max_wrong:
        return c
    own = min_confidence_of(cv_probs, trials, angles, n_stages, params)
    if own["min_confidence"] <= training:  # the grid's top already, or a rounding at the budget's edge
        return c
    return {**own, "chosen_by": f"its own, {own['chosen_by']} (the training units' let through more)"}


def label_of(angles: Sequence[float], angle: float) -> int:
    """The class index of a trained angle."""
    return list(angles).index(float(angle))
