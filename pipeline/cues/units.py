"""Estimator units in the angle estimator: each unit's cast-in preloads shift its rest reading by more
than the needle's weight moves it between angles (docs/physics.md), so the rest reading is compared
after taking out the unit's own offset.

Per unit and channel, the log of the rest reading is modelled as an angle's reference plus the unit's
offset, log rest = mu(angle) + delta(unit); the training units fit both (alternating means, the same
numbers every run), a new unit's offset comes from its calibration insertions at whatever angles it
has (`pipeline.cues.tracker.unit_offset`). Volts divided by exp(delta) are what the angle estimator
is fitted on and fed; the loading snapshots, log(v / rest), do not change.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import pandas as pd

from pipeline.config import CuesParams
from pipeline.cues.fit import _run_evidence
from pipeline.cues.trials import trials_of
from pipeline.vocab import angle_name

ITERATIONS = 50  # alternating means converge in a few for the designs seen here; fixed for determinism

RestLogMeans = dict[str, dict[str, list[float]]]  # {unit: {angle: mean log rest volts per channel}}


def rest_log_means(
    frames_by_angle: Mapping[float, pd.DataFrame], channels: Sequence[str], params: CuesParams
) -> RestLogMeans:
    """Each unit's mean log rest reading per angle (the tracker's own rest rule, trial by trial)."""
    sums: dict[str, dict[str, list[np.ndarray]]] = {}
    for angle, frame in frames_by_angle.items():
        if frame.empty or "unit_id" not in frame.columns:
            continue
        for unit, rows in frame.groupby("unit_id", sort=True):
            for tr in trials_of(rows.reset_index(drop=True), channels, angle):
                rest = _run_evidence(tr.t, tr.volts, params).rest_mean()
                if rest is not None:
                    sums.setdefault(str(unit), {}).setdefault(angle_name(angle), []).append(np.log(rest))
    return {
        u: {a: np.mean(v, axis=0).tolist() for a, v in sorted(per.items(), key=lambda kv: float(kv[0]))}
        for u, per in sorted(sums.items())
    }


def fit_unit_offsets(means: RestLogMeans) -> tuple[dict[str, list[float]], dict[str, list[float]]]:
    """(offsets {unit: delta per channel}, reference {angle: mu per channel}) of the training units,
    offsets centred on zero (an average unit needs no correction)."""
    if not means:
        return {}, {}
    units = sorted(means)
    angles = sorted({a for per in means.values() for a in per}, key=float)
    n_ch = len(next(iter(next(iter(means.values())).values())))
    delta = {u: np.zeros(n_ch) for u in units}
    mu: dict[str, np.ndarray] = {}
    for _ in range(ITERATIONS):
        mu = {
            a: np.mean([np.asarray(means[u][a]) - delta[u] for u in units if a in means[u]], axis=0)
            for a in angles
        }
        delta = {u: np.mean([np.asarray(means[u][a]) - mu[a] for a in means[u]], axis=0) for u in units}
        centre = np.mean([delta[u] for u in units], axis=0)
        delta = {u: d - centre for u, d in delta.items()}
    return {u: delta[u].tolist() for u in units}, {a: mu[a].tolist() for a in angles}


def normalise(
    frame: pd.DataFrame, channels: Sequence[str], offsets: Mapping[str, Sequence[float]]
) -> pd.DataFrame:
    """The frame with each listed unit's channels divided by exp(its offset) (other units unchanged)."""
    if frame.empty or "unit_id" not in frame.columns or not offsets:
        return frame
    out = frame.copy()
    units = out["unit_id"].astype(str)
    for unit, delta in offsets.items():
        mask = (units == unit).to_numpy()
        if mask.any():
            out.loc[mask, list(channels)] = out.loc[mask, list(channels)].to_numpy() / np.exp(
                np.asarray(delta)
            )
    return out


def pack_units(
    offsets: Mapping[str, Sequence[float]], reference: Mapping[str, Sequence[float]]
) -> dict[str, Any]:
    """The cue pack's `units` block: what a client needs to map a unit's rest reading."""
    return {
        "method": "log rest = reference(angle) + offset(unit) per channel; volts / exp(offset) are fed",
        "reference": {a: [float(x) for x in v] for a, v in reference.items()},
        "offsets": {u: [float(x) for x in v] for u, v in offsets.items()},
    }
