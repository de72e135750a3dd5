"""The paper's error measures, eq. (3)-(4), and the angle-gap summaries: small pure functions of
(truth, prediction) arrays or of the score dicts they return."""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import numpy as np

from needlecue_runtime.vocab import AXES

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


def axis_scores(pred: np.ndarray, ref: np.ndarray, axes: Sequence[str] = AXES) -> dict[str, dict[str, float]]:
    """{axis: {"rmse": N, "nrmse_pct": %}} for (n, len(axes)) arrays, columns in `axes` order."""
    p, r = _pair(pred, ref)
    if p.ndim != 2 or p.shape[1] != len(axes):
        raise ValueError(f"expected (n, {len(axes)}) arrays for {list(axes)}, got {p.shape}")
    e, n = rmse(p, r), nrmse_pct(p, r)
    return {a: {"rmse": float(e[i]), "nrmse_pct": float(n[i])} for i, a in enumerate(axes)}


def shared_scores(
    pred: np.ndarray, pred_axes: Sequence[str], ref: np.ndarray, ref_axes: Sequence[str]
) -> dict[str, dict[str, float]]:
    """`axis_scores` on the axes both a prediction (columns `pred_axes`, a model's targets) and a
    reference (columns `ref_axes`, what it recorded) have: a model is scored on no axis it does not
    estimate or the data did not record."""
    common = [a for a in AXES if a in pred_axes and a in ref_axes]
    p = np.asarray(pred)[:, [list(pred_axes).index(a) for a in common]]
    r = np.asarray(ref)[:, [list(ref_axes).index(a) for a in common]]
    return axis_scores(p, r, common)


def mean_known(values: Iterable[float | None]) -> float | None:
    """Mean of the known values; None (unknown) if any is unknown or there are none."""
    vals = list(values)
    if not vals or any(v is None or not math.isfinite(v) for v in vals):
        return None
    return float(np.mean(vals))


def nrmse_of(scores: Mapping[str, Mapping[str, float]]) -> dict[str, float]:
    """{axis: NRMSE %} of one `axis_scores` result, on the axes it has."""
    return {a: scores[a]["nrmse_pct"] for a in AXES if a in scores}


def mean_over_axes(scores: Mapping[str, float | None]) -> float | None:
    """Mean of the force axes' values of one {axis: value} dict (the axes it has)."""
    return mean_known(scores[a] for a in AXES if a in scores)


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
    axes = [a for a in AXES if all(a in c for c in cells)]  # the axes every pair was scored on
    return {a: mean_known(c[a] for c in cells) for a in axes} if cells else {}, len(cells)


def gaps_present(matrix: Mapping[str, Mapping[str, Any]]) -> list[float]:
    """Every gap with at least one pair in an angle-gap matrix, ascending."""
    return sorted({gap_of(t, d) for t, row in matrix.items() for d in row})


def mean_nrmse(scores: Mapping[str, Mapping[str, float]]) -> float:
    """The champion rule's figure: NRMSE averaged over the axes of one `axis_scores` result (fx, fy,
    fz, or those the reference recorded)."""
    return float(np.mean([scores[a]["nrmse_pct"] for a in AXES if a in scores]))
