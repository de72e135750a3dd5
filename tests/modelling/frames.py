"""A small processed split frame for model tests: trials on a 30 Hz grid, three channels."""

from __future__ import annotations

import numpy as np
import pandas as pd

CHANNELS = ["fsr1", "fsr2", "fsr3"]


def make_frame(n_trials: int = 4, n: int = 40, seed: int = 0, batch_id: str = "b1") -> pd.DataFrame:
    """A processed split frame: trials on a 30 Hz grid, three smooth channels, a force that depends
    nonlinearly on them and on their recent history (so every kind has something to learn)."""
    rng = np.random.default_rng(seed)
    parts = []
    for k in range(n_trials):
        t = np.arange(n) / 30.0
        v = 0.5 + 0.2 * np.sin(t[:, None] * (1 + np.arange(3)) + k + seed) + 0.01 * rng.normal(size=(n, 3))
        lagged = np.vstack([v[:1], v[:-1]])
        f = np.column_stack([np.tanh(v[:, 0] - v[:, 1]), v[:, 2] ** 2, lagged[:, 0] + lagged[:, 2]])
        parts.append(
            pd.DataFrame(
                {
                    "batch_id": batch_id,
                    "trial_id": f"t{k:02d}",
                    "angle_deg": 30.0,
                    "tissue_point": "p1",
                    "t_s": t,
                    "phase": "insertion",
                    **{c: v[:, i] for i, c in enumerate(CHANNELS)},
                    "fx": f[:, 0],
                    "fy": f[:, 1],
                    "fz": f[:, 2],
                }
            )
        )
    return pd.concat(parts, ignore_index=True)
