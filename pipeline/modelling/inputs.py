"""Model inputs from processed frames: trial codes, time order, features, windows, scaling.

Shared by training and prediction, so that a model sees at run time exactly what it trained on.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from needlecue_runtime.features import ModelInputs, features
from needlecue_runtime.vocab import TRIAL_KEY


def trial_codes(frame: pd.DataFrame) -> np.ndarray:
    """An integer per row naming its (batch_id, trial_id); a frame without them is one trial."""
    keys = [c for c in TRIAL_KEY if c in frame.columns]
    if not keys or frame.empty:
        return np.zeros(len(frame), dtype=np.int64)
    return frame.groupby(keys, sort=False, dropna=False).ngroup().to_numpy(np.int64)


def sequence_order(codes: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows sorted by (trial, t) and, per sorted row, the sorted position where its trial begins.

    The sort is stable, so rows of one trial with equal (or no) times keep their given order.
    """
    order = np.lexsort((t, codes))
    c = codes[order]
    n = len(c)
    begins = np.ones(n, dtype=bool)
    begins[1:] = c[1:] != c[:-1]
    start = np.maximum.accumulate(np.where(begins, np.arange(n), 0)) if n else np.zeros(0, np.int64)
    return order, start


def window_index(start: np.ndarray, window: int) -> np.ndarray:
    """(n, window) positions of each row's window in trial order: the last `window` rows of its own
    trial ending at the row itself, positions before the trial's start clamped to its first row
    (padding by repetition), so a window never reaches into another trial."""
    n = len(start)
    idx = np.arange(n)[:, None] - (window - 1) + np.arange(window)[None, :]
    return np.maximum(idx, start[:, None])


def column_stats(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Column mean and population std; a constant column gets std 1 (it would divide by zero)."""
    mean = a.mean(axis=0)
    std = a.std(axis=0)
    return mean, np.where(std > 0, std, 1.0)


def times_of(frame: pd.DataFrame) -> np.ndarray:
    """A frame's `t_s` (s), or the row number when it has none."""
    return frame["t_s"].to_numpy(np.float64) if "t_s" in frame.columns else np.arange(len(frame), dtype=float)


def features_of(frame: pd.DataFrame, channels: list[str], spec: ModelInputs) -> np.ndarray:
    """(n, channels) model inputs of a frame's rows (`features.features` per trial), in its order."""
    return features(frame[channels].to_numpy(np.float64), trial_codes(frame), times_of(frame), spec)
