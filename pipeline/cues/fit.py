"""Fitting a cue pack from training splits only: the angle estimator (a linear discriminant per
evidence stage, read through each estimator unit's class means), the preset angle's standard force
profile, the paper-method thresholds per model kind.

A *cue pack* (format `pipeline.cues.tracker.FORMAT`) is a small JSON-able dict shipped with the
preset angle's model; `pipeline.cues.tracker.CueTracker` runs it. What cannot be built from the data
(the angle estimator: one angle only, too few trials, no rest reading; the standard profile: no trial
with a contact) is left null and `unavailable` says why; the tracker falls back to what the pack has.
"""

from __future__ import annotations

import json
import math
import time
import warnings
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np
import pandas as pd

from pipeline.config import CuesParams
from pipeline.cues.reading import distances, log_scores, read_unit
from pipeline.cues.tracker import FORMAT, REFERENCE, VERDICTS, cue_for_deviation
from pipeline.cues.trials import Trial, run_evidence, trials_of, trials_rate_hz
from pipeline.cues.unit_evidence import average_unit, evidence_of, trial_features
from pipeline.frontend import Circuit, circuit_key
from pipeline.logs import Log
from pipeline.vocab import AXES, angle_name, channels_of

Circuits = Mapping[str, Circuit | None]  # {unit_id: its declared circuit (processed front_ends.json)}

Predicted = Mapping[str, Mapping[float, np.ndarray]]  # {kind: {angle: forces on its training frame}}


def _sig(x: float, digits: int = 6) -> float:
    """A float rounded to `digits` significant digits (small, stable JSON)."""
    return float(f"{float(x):.{digits}g}") + 0.0


def _siglist(a: Any, digits: int = 6) -> Any:
    arr = np.asarray(a, dtype=np.float64)
    if arr.ndim == 0:
        return _sig(float(arr), digits)
    return [_siglist(x, digits) for x in arr]


def _softmax(z: np.ndarray) -> np.ndarray:
    z = z - z.max(axis=-1, keepdims=True)
    e = np.exp(z)
    return e / e.sum(axis=-1, keepdims=True)


def _covariance(resid: np.ndarray, shrinkage: str | float) -> np.ndarray:
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


def _template_weight(
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


def _offset_spread(offset: Mapping[str, np.ndarray], precision: np.ndarray) -> float | None:
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


def _fit_stage(
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
        precision = np.linalg.inv(_covariance(resid, params.lda_shrinkage))
    except np.linalg.LinAlgError:
        unshrunk = params.lda_shrinkage != "auto" and float(params.lda_shrinkage) == 0.0
        raise ValueError(
            f"{where}: the trials' scatter has a singular covariance (fewer trials beyond one per unit "
            "and angle than features, or a feature that never varies, such as a channel that reads nothing)"
            + ("; cues.lda_shrinkage 'auto' or a value above 0 shrinks it" if unshrunk else "")
        ) from None
    k = params.unit_template_weight
    if k == "auto":
        k = _template_weight(cells, counts, mu, offset, precision)
    stage = {
        "means": mu,
        "precision": precision,
        "template_weight": k,
        "offset_spread": _offset_spread(offset, precision),
    }
    return {"stage": stage, "cells": {key: (counts[key], cells[key]) for key in keys}}


def _logits(fitted: dict, x: np.ndarray, units: np.ndarray, classes: int) -> np.ndarray:
    """Scores (trials, classes) of trials, each read through its own unit's class means and their
    uncertainty (`pipeline.cues.reading`), as the tracker reads them (before the temperature)."""
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


CALIBRATION_DEPTHS = (1, 2, 3)  # calibration insertions per angle the "calibrated-<k>" readings validate


def _unit_out(
    x: np.ndarray, y: np.ndarray, units: np.ndarray, n_classes: int, params: CuesParams, where: str
) -> dict[str, tuple[list[int], np.ndarray]]:
    """Leave one training unit out, as a new unit meets the estimator: fitted on the other units, the
    unit left out is read calibrated from its first k trials at each angle (k in CALIBRATION_DEPTHS,
    as a lab records k calibration insertions per angle; scored on its other trials: reading
    "calibrated-<k>") and uncalibrated (no cells; scored on all its trials). {reading: (positions in
    `x` scored, their scores (positions, classes) before the temperature)}; empty with fewer than
    two units. `where` names the evidence stage in a fit's errors."""
    out: dict[str, tuple[list[int], list[np.ndarray]]] = {}
    if len(np.unique(units)) < 2:
        return {}
    for held in sorted(set(units.tolist())):
        rest = units != held
        if len(np.unique(y[rest])) < n_classes:
            continue
        left_out = f"{where}, unit {held} left out"
        stage = _fit_stage(x[rest], y[rest], units[rest], n_classes, params, left_out)["stage"]
        mine = np.flatnonzero(~rest)
        by_class: dict[int, list[int]] = {}
        for i in mine.tolist():
            by_class.setdefault(int(y[i]), []).append(i)
        cases = [("uncalibrated", [], mine.tolist())]
        for k in CALIBRATION_DEPTHS:
            if any(len(rows) <= k for rows in by_class.values()):
                continue  # nothing of that class left to score
            used = {i for rows in by_class.values() for i in rows[:k]}
            cells = [(c, float(k), x[rows[:k]].mean(axis=0)) for c, rows in sorted(by_class.items())]
            cases.append((f"calibrated-{k}", cells, [i for i in mine.tolist() if i not in used]))
        for reading, known, scored in cases:
            r = read_unit(
                stage["means"], known, stage["template_weight"], stage["offset_spread"], stage["precision"]
            )
            if not r.known or r.departs:  # nothing bounds this unit (too few units left), or it lies
                continue  # outside what the others cover (the tracker shows it no cue): nothing to validate
            pos, z = out.setdefault(reading, ([], []))
            for i in scored:
                pos.append(i)
                z.append(log_scores(distances(stage["precision"], r.means, x[i]), r, 1.0))
    return {k: (pos, np.asarray(z)) for k, (pos, z) in out.items() if pos}


def _fit_temperature(logits: np.ndarray, y: np.ndarray) -> float:
    """The temperature minimising the cross-validated negative log-likelihood (grid, deterministic)."""
    if np.ptp(logits, axis=1).max(initial=0.0) == 0.0:
        return 1.0  # a flat posterior says nothing of the temperature
    best_t, best_nll = 1.0, math.inf
    for temp in np.geomspace(0.2, 20.0, 81):
        p = _softmax(logits / temp)
        nll = -float(np.mean(np.log(np.clip(p[np.arange(len(y)), y], 1e-300, None))))
        if nll < best_nll - 1e-12:
            best_t, best_nll = float(temp), nll
    return best_t


def fit_angle_estimator(
    train_by_angle: Mapping[float, pd.DataFrame],
    params: CuesParams,
    log: Log | None = None,
    circuits: Circuits | None = None,
) -> dict[str, Any]:
    """The angle estimator on every angle's training trials: per evidence stage, a linear discriminant
    read through each unit's class means (`pipeline.cues.unit_evidence`); its temperature by
    leave-one-batch-out cross-validation, where a held-out batch's unit keeps only its other batches'
    trials."""
    log = log or (lambda _m: None)
    train_by_angle = {float(a): f for a, f in train_by_angle.items()}
    angles = sorted(train_by_angle)
    if len(angles) < 2:
        raise ValueError(
            f"cannot fit the angle estimator: it tells trained angles apart and only "
            f"{', '.join(angle_name(a) + '°' for a in angles) or 'no angle'} has training trials"
        )
    channels = channels_of(train_by_angle[angles[0]])
    for a in angles[1:]:
        if channels_of(train_by_angle[a]) != channels:
            raise ValueError(
                f"cannot fit the angle estimator: {angle_name(a)}° has channels "
                f"{channels_of(train_by_angle[a])}, {angle_name(angles[0])}° has {channels}"
            )
    n_ch = len(channels)
    trials, levels = trial_features(train_by_angle, channels, params, circuits)
    label = {a: k for k, a in enumerate(angles)}
    y_all = np.array([label[t.angle] for t in trials], dtype=np.int64)
    g_all = np.array([t.batch for t in trials])
    u_all = np.array([t.unit for t in trials])
    st_all = np.array([t.stage for t in trials], dtype=np.int64)
    out_stages = []
    # per reading (pipeline.cues.tracker.READINGS): (trial, stage, its cross-validated P(angle))
    cv_probs: dict[str, list[tuple[int, int, np.ndarray]]] = {"training": []}
    for j in range(len(levels) + 1):
        sel = np.flatnonzero(st_all >= j)
        y, g, u = y_all[sel], g_all[sel], u_all[sel]
        if len(np.unique(y)) < len(angles) or len(sel) <= len(angles) + 1:
            log(
                f"angle estimator: stage {j} has too few trials of every angle ({len(sel)}), stages stop here"
            )
            break
        x = np.array([trials[i].at(j, n_ch) for i in sel])
        fitted = _fit_stage(x, y, u, len(angles), params, f"evidence stage {j}")
        temp, cv_acc = 1.0, None
        folds = np.unique(g) if len(np.unique(g)) >= 2 else None
        fold_of = g if folds is not None else (np.arange(len(sel)) % 5).astype(str)
        logits = np.full((len(sel), len(angles)), np.nan)
        for f in np.unique(fold_of):
            tr_m, te_m = fold_of != f, fold_of == f
            if len(np.unique(y[tr_m])) < len(angles):
                continue
            held = f"batch {f}" if folds is not None else f"fold {f} of 5"
            where = f"evidence stage {j}, {held} left out"
            fold = _fit_stage(x[tr_m], y[tr_m], u[tr_m], len(angles), params, where)
            logits[te_m] = _logits(fold, x[te_m], u[te_m], len(angles))
        ok = np.isfinite(logits).all(axis=1)
        if ok.any():
            cv_acc = float(np.mean(np.argmax(logits[ok], axis=1) == y[ok]))
            if params.calibrate_temperature:
                temp = _fit_temperature(logits[ok], y[ok])
            probs = _softmax(logits[ok] / temp)
            cv_probs["training"] += [(int(i), j, p) for i, p in zip(sel[ok], probs, strict=True)]
        temps = {}
        for reading, (pos, z) in _unit_out(x, y, u, len(angles), params, f"evidence stage {j}").items():
            t_r = _fit_temperature(z, y[pos]) if params.calibrate_temperature else 1.0
            temps[reading] = _sig(t_r)
            probs = _softmax(z / t_r)
            cv_probs.setdefault(reading, []).extend(
                (int(sel[i]), j, p) for i, p in zip(pos, probs, strict=True)
            )
        stage = fitted["stage"]
        k, spread = stage["template_weight"], stage["offset_spread"]
        out_stages.append(
            {
                "means": _siglist(stage["means"]),
                "precision": _siglist(stage["precision"]),
                "template_weight": None if k is None else _sig(k),
                "offset_spread": None if spread is None else _sig(spread),
                "temperature": _sig(temp),
                # a unit left out of training, read calibrated or not (leave-one-unit-out; none with one unit)
                "temperatures": temps,
                "outside_limit": None
                if (lim := outside_limit(len(sel), len(angles), x.shape[1])) is None
                else _sig(lim),
                "n_train": len(sel),
                "cv_accuracy": None if cv_acc is None else _sig(cv_acc, 4),
            }
        )
        log(
            f"angle estimator: stage {j} ({len(sel)} trials) cross-validated accuracy "
            f"{'n/a' if cv_acc is None else f'{cv_acc:.2f}'}, temperature {temp:.3g}, template weight "
            f"{'none' if k is None else f'{k:.3g}'}, offset spread "
            f"{'none' if spread is None else f'{spread:.3g}'}"
        )
    if not out_stages:
        rested = ", ".join(f"{angle_name(a)}° {int(np.sum(y_all == k))}" for k, a in enumerate(angles))
        raise ValueError(
            "cannot fit the angle estimator: it needs training trials with a rest reading at every "
            f"angle, more than {len(angles) + 1} in all (has {rested})"
        )
    # The confidence is chosen on the training units' batches, where cross-validation reads units as
    # the tracker reads them; a unit left out is read with that value unless its own cross-validation
    # says otherwise (`reading_confidence`).
    confidence = {"training": _min_confidence(cv_probs["training"], trials, angles, len(out_stages), params)}
    training = confidence["training"]["min_confidence"]
    for reading, probs in cv_probs.items():
        if reading != "training":
            confidence[reading] = reading_confidence(probs, trials, angles, len(out_stages), params, training)
    for reading, c in confidence.items():
        log(
            f"angle estimator, {reading} unit: a cue needs P >= {c['min_confidence']:g} ({c['chosen_by']}); "
            f"cross-validated, a wrong cue in {100 * c['cv_wrong_frames']:.2f} % of insertion frames, "
            f"a cue in {100 * c['cv_coverage']:.1f} %"
        )
    return {
        "method": "Gaussian classes per evidence stage (shared shrunk covariance, uniform priors), each "
        "unit read through its own class means and their uncertainty (pipeline.cues.reading), "
        "softmax(scores / temperature)",
        "features": "per channel, the log of the rest signal (the FSR's conductance through each unit's "
        "declared front end; the volts where none is declared), then the unit direction of the "
        "signal's change since rest when the norm of log(signal / rest) first reaches each level",
        "classes_deg": angles,
        "levels": [float(x) for x in levels[: len(out_stages) - 1]],
        "stages": out_stages,
        "units": {
            unit: {a: {"n": e["n"], "means": [_siglist(m) for m in e["means"]]} for a, e in per.items()}
            for unit, per in evidence_of(trials, n_ch).items()
        },
        "cv": "leave-one-batch-out" if len(np.unique(g_all)) >= 2 else "5-fold by trial",
        "confidence": confidence,
    }


CONFIDENCE_GRID = tuple(round(0.5 + 0.01 * i, 2) for i in range(50))  # 0.50 .. 0.99


def _min_confidence(
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
        "min_confidence": _sig(grid[k], 4),
        "chosen_by": how,
        "cv_wrong_frames": _sig(rate[k] if total else 0.0, 4),
        "cv_coverage": _sig(shown[k] / total if total else 0.0, 4),
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
    "auto": the least value that holds its own budget, as `_min_confidence` chooses it, where that is
    above `training`. Measured on `power-law` with three calibration insertions per angle, the training
    units' value let 3.7 % of a new unit's insertions end on a wrong cue (docs/units.md)."""
    at = params.model_copy(update={"min_confidence": training})
    c = {
        **_min_confidence(cv_probs, trials, angles, n_stages, at),
        "chosen_by": "the training units' (its own temperature puts it on their footing)",
    }
    if params.min_confidence != "auto" or c["cv_wrong_frames"] <= params.max_wrong:
        return c
    own = _min_confidence(cv_probs, trials, angles, n_stages, params)
    if own["min_confidence"] <= training:  # the grid's top already, or a rounding at the budget's edge
        return c
    return {**own, "chosen_by": f"its own, {own['chosen_by']} (the training units' let through more)"}


def label_of(angles: Sequence[float], angle: float) -> int:
    """The class index of a trained angle."""
    return list(angles).index(float(angle))


def try_fit_angle_estimator(
    train_by_angle: Mapping[float, pd.DataFrame],
    params: CuesParams,
    log: Log | None = None,
    circuits: Circuits | None = None,
) -> tuple[dict[str, Any] | None, str | None]:
    """(`fit_angle_estimator` result, None), or (None, why it cannot be fitted) with a warning logged:
    the cues then fall back to the paper's profile method."""
    log = log or (lambda _m: None)
    try:
        return fit_angle_estimator(train_by_angle, params, log, circuits), None
    except (ValueError, np.linalg.LinAlgError) as e:
        reason = str(e).removeprefix("cannot fit the angle estimator: ")
    log(f"warning: no angle estimator ({reason}): the cues fall back to the paper's profile method")
    return None, reason


def _standard_profile(trials: Sequence[Trial], params: CuesParams) -> tuple[dict[str, Any], list[int]]:
    """Mean and spread of the reference force against time since the detected contact."""
    grid = np.arange(0.0, params.profile_horizon_s + 1e-9, params.profile_dt_s)
    # the preset angle's axes (split gives an angle's trials one set): what its models estimate
    axes = trials[0].axes if trials else AXES
    rows, contacts = [], []
    for tr in trials:
        ev = run_evidence(tr, params)
        contacts.append(ev.contact_i)
        if ev.contact_t is None:
            continue
        tt = ev.contact_t + grid
        prof = np.stack([np.interp(tt, tr.t, tr.force[:, k], right=np.nan) for k in range(len(axes))], axis=1)
        rows.append(prof)
    if not rows:
        raise ValueError("no training trial of the preset angle has a detectable contact")
    stack = np.stack(rows)  # (trials, grid, 3)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # grid points no trial reaches
        mean = np.nanmean(stack, axis=0)
        sd = np.nanstd(stack, axis=0)
    # grid points no trial reaches: hold the last known value
    for k in range(1, len(grid)):
        bad = ~np.isfinite(mean[k])
        mean[k, bad], sd[k, bad] = mean[k - 1, bad], sd[k - 1, bad]
    mean, sd = np.nan_to_num(mean), np.nan_to_num(sd)
    return (
        {
            "dt_s": float(params.profile_dt_s),
            "axes": list(axes),
            "mean_n": _siglist(mean, 5),
            "sd_n": _siglist(sd, 5),
            "floor_n": float(params.profile_floor_n),
            "n_trials": len(rows),
            "time_origin": "the contact detected from the estimator's volts (as at run time)",
        },
        contacts,
    )


def _profile_scores(
    t: np.ndarray,
    force: np.ndarray,
    contact_i: int,
    mean: np.ndarray,
    sde: np.ndarray,
    dt: float,
    horizon: float,
) -> np.ndarray:
    """The paper-method distance at every frame (NaN before contact), as the tracker computes it."""
    out = np.full(len(t), np.nan)
    if contact_i < 0:
        return out
    tau = t[contact_i:] - t[contact_i]
    inside = tau <= horizon + 1e-9
    gi = np.minimum((tau / dt + 0.5).astype(np.int64), len(mean) - 1)
    z2 = np.sum(((force[contact_i:] - mean[gi]) / sde[gi]) ** 2, axis=1) * inside
    cum = np.cumsum(z2)
    cnt = np.cumsum(inside)
    out[contact_i:] = np.sqrt(cum / (force.shape[1] * np.maximum(cnt, 1)))
    return out


def _best_thresholds(scores: Sequence[np.ndarray]) -> tuple[float, float, float]:
    """(continue_below, stop_from, balanced accuracy) maximising the per-frame balanced accuracy
    over the three true cues (classes without frames are left out of the mean)."""
    present = [s for s in scores if len(s)]
    if not present:
        return math.inf, math.inf, math.nan
    allv = np.concatenate(present)
    cand = np.unique(np.quantile(allv, np.linspace(0, 1, 241)))
    cand = np.concatenate([cand, [cand[-1] * 1.001 + 1e-9]])
    cdf = [np.searchsorted(np.sort(s), cand, side="left") / max(len(s), 1) for s in scores]
    # recall(continue)=P(s<t1), recall(correct)=P(t1<=s<t2), recall(stop)=P(s>=t2)
    best = (-1.0, 0, 0)
    for i in range(len(cand)):
        j = np.arange(i, len(cand))
        parts = []
        if len(scores[0]):
            parts.append(np.full(len(j), cdf[0][i]))
        if len(scores[1]):
            parts.append(cdf[1][j] - cdf[1][i])
        if len(scores[2]):
            parts.append(1.0 - cdf[2][j])
        bal = np.mean(parts, axis=0)
        k = int(np.argmax(bal))
        if bal[k] > best[0] + 1e-12:
            best = (float(bal[k]), i, int(j[k]))
    return float(cand[best[1]]), float(cand[best[2]]), best[0]


def build_cue_pack(
    train_by_angle: Mapping[float, pd.DataFrame],
    preset_angle: float,
    params: CuesParams,
    predicted: Predicted | None = None,
    log: Log | None = None,
    angle_estimator: Mapping[str, Any] | None = None,
    *,
    estimator_unavailable: str | None = None,
    circuits: Circuits | None = None,
) -> dict[str, Any]:
    """The cue pack of one preset angle, from training splits only (see the module docstring).

    `train_by_angle`: every angle's training frame (the angle estimator needs them all).
    `predicted`: {kind: {angle: forces}}, the preset angle's model of each kind on every angle's
    training frame (rows in frame order), used to calibrate the paper-method thresholds per kind;
    None calibrates them on the reference force alone (an ideal model).
    `angle_estimator`: a `fit_angle_estimator` result to reuse (it is the same for every preset);
    `estimator_unavailable`: why there is none (then none is fitted). Without either, it is fitted here.
    `circuits`: {unit_id: its declared circuit}; the pack records the one its training units share.

    What cannot be built from the data (the angle estimator: one angle only, too few trials, no rest
    reading; the standard profile: no trial with a contact) is left null, and `unavailable` says why
    (the key is there only then); `CueTracker` falls back to what the pack has.
    """
    log = log or (lambda _m: None)
    train_by_angle = {float(a): f for a, f in train_by_angle.items()}
    preset = float(preset_angle)
    if preset not in train_by_angle or train_by_angle[preset].empty:
        raise ValueError(f"no training data for the preset angle {preset:g}°")
    channels = channels_of(train_by_angle[preset])
    if not channels:
        raise ValueError("the training frames have no estimator channel")
    for a, f in train_by_angle.items():
        if channels_of(f) != channels:
            raise ValueError(f"angle {a:g}° has channels {channels_of(f)}, the preset has {channels}")
    angles = sorted(train_by_angle)
    trials = {a: trials_of(train_by_angle[a], channels, a, circuits) for a in angles}
    rate = trials_rate_hz(trials[preset])
    unavailable: dict[str, str] = {}

    try:
        profile: dict[str, Any] | None = _standard_profile(trials[preset], params)[0]
    except ValueError as e:
        profile = None
        unavailable["standard_profile"] = str(e)
        log(f"warning: preset {preset:g}°: no standard profile ({e}): no paper-method cue in its pack")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN reference force
        norms = [np.nanmax(np.linalg.norm(tr.force, axis=1)) for tr in trials[preset] if len(tr.t)]
    peak = float(np.nanmax(norms)) if norms and np.isfinite(norms).any() else math.nan

    predicted = dict(predicted or {})
    for kind, by_angle in predicted.items():
        if missing := [angle_name(a) for a in angles if a not in by_angle]:
            raise ValueError(
                f"no {kind} predictions of the {preset:g}° model on the training frames of {missing}"
            )
    thresholds: dict[str, Any] = {}
    if profile is not None:
        mean = np.asarray(profile["mean_n"])
        sde = np.sqrt(np.asarray(profile["sd_n"]) ** 2 + params.profile_floor_n**2)
        contacts = {a: [run_evidence(tr, params).contact_i for tr in trials[a]] for a in angles}
        for kind in [REFERENCE, *predicted]:
            by_cue: dict[str, list[np.ndarray]] = {c: [] for c in VERDICTS}
            for a in angles:
                if kind == REFERENCE:
                    forces = [tr.force_on(profile["axes"]) for tr in trials[a]]
                    if any(f is None for f in forces):  # another angle's reference records other axes
                        continue
                else:
                    pred = np.asarray(predicted[kind][a], dtype=float)
                    forces = [pred[tr.rows] for tr in trials[a]]
                cue = cue_for_deviation(a - preset, params.continue_below_deg, params.stop_from_deg)
                for tr, f, ci in zip(trials[a], forces, contacts[a], strict=True):
                    if ci < 0 or tr.ins_end < 0:
                        continue
                    s = _profile_scores(tr.t, f, ci, mean, sde, params.profile_dt_s, params.profile_horizon_s)
                    frames = (tr.t >= tr.t[ci] + params.min_profile_s - 1e-9) & (
                        np.arange(len(tr.t)) <= tr.ins_end
                    )
                    by_cue[cue].append(s[frames])
            absent = [c for c in VERDICTS if not by_cue[c]]
            if absent and kind == REFERENCE:
                log(
                    f"warning: preset {preset:g}°: no training trial whose true cue is {' or '.join(absent)} "
                    "(no angle that far off): the paper-method thresholds are calibrated without them"
                )
            t1, t2, bal = _best_thresholds(
                [np.concatenate(by_cue[c]) if by_cue[c] else np.zeros(0) for c in VERDICTS]
            )
            if not (math.isfinite(t1) and math.isfinite(t2)):
                why = (
                    f"no training frame to calibrate the {kind} thresholds on (trials need a contact and "
                    f"frames labelled 'insertion' at least {params.min_profile_s:g} s after it)"
                )
                unavailable[f"thresholds.profile.{kind}"] = why
                log(f"warning: preset {preset:g}°: {why}")
                continue
            thresholds[kind] = {
                "continue_below": _sig(t1),
                "stop_from": _sig(t2),
                "train_balanced_accuracy": _sig(bal, 4),
            }
            log(
                f"preset {preset:g}°: paper-method thresholds ({kind}) {t1:.3g} / {t2:.3g}, "
                f"per-frame balanced accuracy on training {bal:.2f}"
            )

    estimator: dict[str, Any] | None
    if angle_estimator is not None:
        estimator = dict(angle_estimator)
    elif estimator_unavailable is not None:
        estimator = None
    else:
        estimator, estimator_unavailable = try_fit_angle_estimator(train_by_angle, params, log, circuits)
    if estimator is None:
        unavailable["angle_estimator"] = estimator_unavailable or "not fitted"
    pack = {
        "format": FORMAT,
        "preset_angle_deg": preset,
        "angles": angles,
        "channels": list(channels),
        "rate_hz": _sig(rate) if math.isfinite(rate) else None,
        "standard_profile": profile,
        "angle_estimator": estimator,
        "thresholds": {
            "profile": thresholds,
            "force_limit_n": _sig(params.force_margin * peak) if math.isfinite(peak) else None,
            "continue_below_deg": float(params.continue_below_deg),
            "stop_from_deg": float(params.stop_from_deg),
        },
        "training": {
            "trials_per_angle": {angle_name(a): len(trials[a]) for a in angles},
            "batches": sorted({tr.batch for a in angles for tr in trials[a]}),
        },
        "params": params.model_dump(mode="json"),
        # the circuit the training units share (their loading directions are in its conductance)
        "front_end": _shared_circuit(trials, angles),
    }
    if unavailable:
        pack["unavailable"] = dict(sorted(unavailable.items()))
    return pack


def _shared_circuit(
    trials: Mapping[float, Sequence[Trial]], angles: Sequence[float]
) -> dict[str, Any] | None:
    """The circuit every training trial's unit declares, as stored (None if any declares none or
    they differ: then the directions of a unit without its own are read in volts)."""
    found = {circuit_key(tr.front_end) for a in angles for tr in trials[a]}
    return json.loads(found.pop()) if len(found) == 1 and "" not in found else None


def build_packs(
    train_by_angle: Mapping[float, pd.DataFrame],
    predicted_for: Callable[[float], Predicted],
    params: CuesParams,
    log: Log,
    circuits: Circuits | None = None,
) -> dict[float, dict[str, Any]]:
    """The cue pack of every angle with training rows; `predicted_for(preset)` gives that preset's
    models' predictions on every angle's training frame ({kind: {angle: forces}}); `circuits` is
    {unit_id: its declared circuit}."""
    estimator, no_estimator = try_fit_angle_estimator(train_by_angle, params, log, circuits)
    packs: dict[float, dict[str, Any]] = {}
    for preset in train_by_angle:
        started = time.perf_counter()
        packs[preset] = build_cue_pack(
            train_by_angle,
            preset,
            params,
            predicted_for(preset) or None,
            log=log,
            angle_estimator=estimator,
            estimator_unavailable=no_estimator,
            circuits=circuits,
        )
        log(f"pack for {angle_name(preset)}° built ({time.perf_counter() - started:.1f} s)")
    return packs


def pack_json(pack: Mapping[str, Any]) -> str:
    """A pack's file text: compact, sorted, strict JSON (what the client's model metadata carries)."""
    return json.dumps(pack, sort_keys=True, separators=(",", ":"), ensure_ascii=False, allow_nan=False) + "\n"
