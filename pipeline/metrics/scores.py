"""The paper's error measures, eq. (3)-(4), and the angle-gap summaries: small pure functions of
(truth, prediction) arrays or of the score dicts they return."""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np

from pipeline.vocab import AXES

GAP_TOL = 1e-6  # degrees; angles are parsed from folder names, so only rounding noise


def _pair(pred: np.ndarray, ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    p, r = np.asarray(pred, dtype=float), np.asarray(ref, dtype=float)
    if p.shape != r.shape:
        raise ValueError(f"prediction shape {p.shape} differs from reference shape {r.shape}")
    if p.shape[0] == 0:
        raise ValueError("no samples to score")
    return p, r


def rmse(pred: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Eq. (3): sqrt(mean((pred − ref)²)) over samples (axis 0), one value per column."""
    p, r = _pair(pred, ref)
    return np.sqrt(np.mean((p - r) ** 2, axis=0))


def nrmse_pct(pred: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Eq. (4): 100 · RMSE / (max(ref) − min(ref)) per column; NaN where the reference is constant."""
    p, r = _pair(pred, ref)
    span = np.max(r, axis=0) - np.min(r, axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        out = 100.0 * rmse(p, r) / span
    return np.where(span > 0, out, np.nan)


def axis_scores(pred: np.ndarray, ref: np.ndarray) -> dict[str, dict[str, float]]:
    """{axis: {"rmse": N, "nrmse_pct": %}} for (n, 3) arrays in fx, fy, fz order."""
    p, r = _pair(pred, ref)
    if p.ndim != 2 or p.shape[1] != len(AXES):
        raise ValueError(f"expected (n, {len(AXES)}) arrays, got {p.shape}")
    e, n = rmse(p, r), nrmse_pct(p, r)
    return {a: {"rmse": float(e[i]), "nrmse_pct": float(n[i])} for i, a in enumerate(AXES)}


def mean_known(values: Iterable[float | None]) -> float | None:
    """Mean of the known values; None (unknown) if any is unknown or there are none."""
    vals = list(values)
    if not vals or any(v is None or not math.isfinite(v) for v in vals):
        return None
    return float(np.mean(vals))


def mean_over_axes(scores: Mapping[str, float | None]) -> float | None:
    """Mean of the fx, fy, fz values of one {axis: value} dict."""
    return mean_known(scores.get(a) for a in AXES)


def gap_of(train_angle: str, data_angle: str) -> float:
    """Absolute angle gap in degrees, rounded so 15 == |30 − 45| exactly."""
    return round(abs(float(train_angle) - float(data_angle)), 6)


def gap_summary(
    matrix: Mapping[str, Mapping[str, Mapping[str, float | None]]], gap: float
) -> tuple[dict[str, float | None], int]:
    """Per-axis mean NRMSE over every (train, data) pair of `matrix` whose gap is `gap`, and the
    pair count (the paper's Table II rows; ±gap both count)."""
    cells = [
        scores
        for train_angle, row in matrix.items()
        for data_angle, scores in row.items()
        if abs(gap_of(train_angle, data_angle) - gap) <= GAP_TOL
    ]
    return {a: mean_known(c.get(a) for c in cells) for a in AXES} if cells else {}, len(cells)


def gaps_present(matrix: Mapping[str, Mapping[str, Any]]) -> list[float]:
    """Every gap with at least one pair in an angle-gap matrix, ascending."""
    return sorted({gap_of(t, d) for t, row in matrix.items() for d in row})


def mean_nrmse(scores: Mapping[str, Mapping[str, float]]) -> float:
    """The champion rule's figure: NRMSE averaged over fx, fy, fz of one `axis_scores` result."""
    return float(np.mean([scores[a]["nrmse_pct"] for a in AXES]))
