"""Fitting the angle estimator on every angle's training trials: per evidence stage a linear
discriminant (`pipeline.cues.discriminant`), its temperature and the confidence a cue needs cross-
validated (`pipeline.cues.confidence`), for a training unit and for a unit left out, read calibrated or
not. The result is the pack's `angle_estimator` (`needlecue_runtime.cues.pack.AngleEstimator`).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import pandas as pd

from needlecue_runtime.cues.pack import sig, siglist
from needlecue_runtime.cues.reading import distances, log_scores, read_unit
from needlecue_runtime.frontend import Circuit
from needlecue_runtime.vocab import angle_name, channels_of
from pipeline.config import CuesParams
from pipeline.cues.confidence import fit_temperature, min_confidence_of, reading_confidence, softmax
from pipeline.cues.discriminant import fit_stage, outside_limit, stage_logits
from pipeline.cues.unit_evidence import evidence_of, trial_features
from pipeline.logs import Log

Circuits = Mapping[str, Circuit | None]  # {unit_id: its declared circuit (processed front_ends.json)}

CALIBRATION_DEPTHS = (1, 2, 3)  # calibration insertions per angle the "calibrated-<k>" readings validate


def unit_out(
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
        stage = fit_stage(x[rest], y[rest], units[rest], n_classes, params, left_out)["stage"]
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
    # per reading (needlecue_runtime.cues.pack.READINGS): (trial, stage, its cross-validated P(angle))
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
        fitted = fit_stage(x, y, u, len(angles), params, f"evidence stage {j}")
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
            fold = fit_stage(x[tr_m], y[tr_m], u[tr_m], len(angles), params, where)
            logits[te_m] = stage_logits(fold, x[te_m], u[te_m], len(angles))
        ok = np.isfinite(logits).all(axis=1)
        if ok.any():
            cv_acc = float(np.mean(np.argmax(logits[ok], axis=1) == y[ok]))
            if params.calibrate_temperature:
                temp = fit_temperature(logits[ok], y[ok])
            probs = softmax(logits[ok] / temp)
            cv_probs["training"] += [(int(i), j, p) for i, p in zip(sel[ok], probs, strict=True)]
        temps = {}
        for reading, (pos, z) in unit_out(x, y, u, len(angles), params, f"evidence stage {j}").items():
            t_r = fit_temperature(z, y[pos]) if params.calibrate_temperature else 1.0
            temps[reading] = sig(t_r)
            probs = softmax(z / t_r)
            cv_probs.setdefault(reading, []).extend(
                (int(sel[i]), j, p) for i, p in zip(pos, probs, strict=True)
            )
        stage = fitted["stage"]
        k, spread = stage["template_weight"], stage["offset_spread"]
        out_stages.append(
            {
                "means": siglist(stage["means"]),
                "precision": siglist(stage["precision"]),
                "template_weight": None if k is None else sig(k),
                "offset_spread": None if spread is None else sig(spread),
                "temperature": sig(temp),
                # a unit left out of training, read calibrated or not (leave-one-unit-out; none with one unit)
                "temperatures": temps,
                "outside_limit": None
                if (lim := outside_limit(len(sel), len(angles), x.shape[1])) is None
                else sig(lim),
                "n_train": len(sel),
                "cv_accuracy": None if cv_acc is None else sig(cv_acc, 4),
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
    confidence = {
        "training": min_confidence_of(cv_probs["training"], trials, angles, len(out_stages), params)
    }
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
        "unit read through its own class means and their uncertainty (needlecue_runtime.cues.reading), "
        "softmax(scores / temperature)",
        "features": "per channel, the log of the rest signal (the FSR's conductance through each unit's "
        "declared front end; the volts where none is declared), then the unit direction of the "
        "signal's change since rest when the norm of log(signal / rest) first reaches each level",
        "classes_deg": angles,
        "levels": [float(x) for x in levels[: len(out_stages) - 1]],
        "stages": out_stages,
        "units": {
            unit: {a: {"n": e["n"], "means": [siglist(m) for m in e["means"]]} for a, e in per.items()}
            for unit, per in evidence_of(trials, n_ch).items()
        },
        "cv": "leave-one-batch-out" if len(np.unique(g_all)) >= 2 else "5-fold by trial",
        "confidence": confidence,
    }


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
