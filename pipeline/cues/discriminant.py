"""One evidence stage of the angle estimator: Gaussian classes with one shrunk covariance, the average
unit's class means, and how far units depart from them (the template weight, the offsets' spread);
each trial read through its own unit's class means (`needlecue_runtime.cues.reading`), as the tracker
reads it.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from needlecue_runtime.cues.reading import distances, log_scores, read_unit
from pipeline.config import CuesParams
from pipeline.cues.unit_evidence import average_unit


def covariance(resid: np.ndarray, shrinkage: str | float) -> np.ndarray:
    """The scatter's covariance, shrunk as scikit-learn's LDA does (on standardised features;
    "auto": Ledoit-Wolf)."""
    from sklearn.covariance import empirical_covariance, ledoit_wolf, shrunk_covariance

    sd = resid.std(axis=0)
    sd[sd == 0] = 1.0
    z = resid / sd
    if shrinkage == "auto":
        cov = ledoit_wolf(z, assume_centered=True)[0]
    else:
        cov = shrunk_covariance(empirical_covariance(z, assume_centered=True), float(shrinkage))
    return cov * sd[:, None] * sd[None, :]


def template_weight(
    cells: Mapping[tuple[str, int], np.ndarray],
    counts: Mapping[tuple[str, int], int],
    mu: np.ndarray,
    offset: Mapping[str, np.ndarray],
    precision: np.ndarray,
) -> float | None:
    """k = scatter variance / the variance of the units' own departures at an angle (empirical Bayes,
    in the scatter's whitened units): how many trials a unit needs at an angle before they count as
    much as the average unit's shifted mean. None when the departures cannot be told from scatter
    (one unit, or too few cells): then no unit's trials pull its means."""
    free = len(cells) - len(mu) - len({u for u, _ in cells}) + 1  # cells less the means and offsets fitted
    if free <= 0:
        return None
    width = mu.shape[1]
    excess = 0.0
    for (u, c), m in cells.items():
        r = m - mu[c] - offset[u]
        excess += float(r @ precision @ r) / width - 1.0 / counts[(u, c)]
    tau2 = excess / free
    return None if tau2 <= 0 else 1.0 / tau2


MIN_UNITS_FOR_SPREAD = 3  # training units needed before their spread bounds a new unit's offset


def offset_spread(offset: Mapping[str, np.ndarray], precision: np.ndarray) -> float | None:
    """The variance of the units' offsets per feature, in the scatter's whitened units. None with
    fewer than MIN_UNITS_FOR_SPREAD units: nothing, or one difference, says how far a unit may sit
    from the average (two similar units would call a third that differs "close to average", shrink its
    calibration towards them, and show it confident wrong cues: measured with est-sim-002 left out of
    the defaults' three, 11 % of insertions ending on a wrong cue). A calibrated unit is then shifted
    by its whole offset, and an uncalibrated one gets no angle cue."""
    if len(offset) < MIN_UNITS_FOR_SPREAD:
        return None
    width = precision.shape[0]
    total = sum(float(d @ precision @ d) for d in offset.values())
    return total / (width * (len(offset) - 1))


def fit_stage(
    x: np.ndarray, y: np.ndarray, units: np.ndarray, n_classes: int, params: CuesParams, where: str
) -> dict:
    """One evidence stage: the average unit's class means, the shared precision, the template weight,
    the units' offset spread, and the cells {(unit, class): (n, mean)} of the trials given. `where`
    names the fit in its errors (the evidence stage, and what cross-validation left out)."""
    keys = sorted(set(zip(units.tolist(), y.tolist(), strict=True)))
    member = {key: (units == key[0]) & (y == key[1]) for key in keys}
    cells = {key: x[m].mean(axis=0) for key, m in member.items()}
    counts = {key: int(m.sum()) for key, m in member.items()}
    mu, offset = average_unit(cells, n_classes)
    resid = x.copy()
    for key, m in member.items():
        resid[m] -= cells[key]
    if all(n == 1 for n in counts.values()):  # every residual is 0: no shrinkage makes a covariance
        raise ValueError(
            f"{where}: the trials fitted hold one per unit and angle: nothing shows how trials scatter "
            "around their means"
        )
    try:
        precision = np.linalg.inv(covariance(resid, params.lda_shrinkage))
    except np.linalg.LinAlgError:
        unshrunk = params.lda_shrinkage != "auto" and float(params.lda_shrinkage) == 0.0
        raise ValueError(
            f"{where}: the trials' scatter has a singular covariance (fewer trials beyond one per unit "
            "and angle than features, or a feature that never varies, such as a channel that reads nothing)"
            + ("; cues.lda_shrinkage 'auto' or a value above 0 shrinks it" if unshrunk else "")
        ) from None
    k = params.unit_template_weight
    if k == "auto":
        k = template_weight(cells, counts, mu, offset, precision)
    stage = {
        "means": mu,
        "precision": precision,
        "template_weight": k,
        "offset_spread": offset_spread(offset, precision),
    }
    return {"stage": stage, "cells": {key: (counts[key], cells[key]) for key in keys}}


def stage_logits(fitted: dict, x: np.ndarray, units: np.ndarray, classes: int) -> np.ndarray:
    """Scores (trials, classes) of trials, each read through its own unit's class means and their
    uncertainty (`needlecue_runtime.cues.reading`), as the tracker reads them (before the temperature)."""
    stage = fitted["stage"]
    out = np.empty((len(x), classes))
    for u in sorted(set(units.tolist())):
        cells = [(c, float(n), m) for (u2, c), (n, m) in fitted["cells"].items() if u2 == u]
        reading = read_unit(stage["means"], cells, stage["template_weight"], stage["offset_spread"])
        for i in np.flatnonzero(units == u):
            out[i] = log_scores(distances(stage["precision"], reading.means, x[i]), reading, 1.0)
    return out


OUTSIDE_P = 0.001  # the share of trials of a trained angle the "outside" test may call outside


def outside_limit(n_trials: int, n_classes: int, width: int) -> float | None:
    """The squared distance from its class mean that a new trial of a trained angle exceeds with
    probability OUTSIDE_P, in the scatter's units, when the means and the scatter are estimated from
    `n_trials` trials of `n_classes` classes (Hotelling's predictive distribution: a scaled F, wider
    than chi-square when the trials are few); None when the trials are too few to say."""
    from scipy.stats import f

    dof = n_trials - n_classes - width + 1
    if dof < 1:
        return None
    scale = width * (n_trials - n_classes) / dof * (1.0 + n_classes / n_trials)
    return float(scale * f.ppf(1.0 - OUTSIDE_P, width, dof))
