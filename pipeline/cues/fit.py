"""Fitting a cue pack from training splits only: the angle estimator (one LDA per evidence stage),
the preset angle's standard force profile, the paper-method thresholds per model kind.

A *cue pack* (format "needlecue-cues/1") is a small JSON-able dict shipped with the preset angle's
model; `pipeline.cues.tracker.CueTracker` runs it. What cannot be built from the data (the angle
estimator: one angle only, too few trials, no rest reading; the standard profile: no trial with a
contact) is left null and `unavailable` says why; the tracker falls back to what the pack has.
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
from pipeline.cues.tracker import FORMAT, REFERENCE, VERDICTS, Evidence, cue_for_deviation
from pipeline.cues.trials import Trial, trials_of, trials_rate_hz
from pipeline.vocab import AXES, angle_name, channels_of

Log = Callable[[str], None]
Predicted = Mapping[str, Mapping[float, np.ndarray]]  # {kind: {angle: forces on its training frame}}


def _sig(x: float, digits: int = 6) -> float:
    """A float rounded to `digits` significant digits (small, stable JSON)."""
    return float(f"{float(x):.{digits}g}") + 0.0


def _siglist(a: Any, digits: int = 6) -> Any:
    arr = np.asarray(a, dtype=np.float64)
    if arr.ndim == 0:
        return _sig(float(arr), digits)
    return [_siglist(x, digits) for x in arr]


def _run_evidence(t: np.ndarray, volts: np.ndarray, params: CuesParams) -> Evidence:
    """The evidence of a whole trial (causal code, fed frame by frame until every level is reached)."""
    ev = Evidence(
        volts.shape[1],
        params.evidence_levels,
        params.contact_threshold,
        params.contact_samples,
        params.min_rest_s,
    )
    rows = volts.tolist()
    for i, (ti, vi) in enumerate(zip(t.tolist(), rows, strict=True)):
        ev.push(ti, vi, None, i)
        if ev.stage >= len(params.evidence_levels):
            break
    return ev


def _softmax(z: np.ndarray) -> np.ndarray:
    z = z - z.max(axis=-1, keepdims=True)
    e = np.exp(z)
    return e / e.sum(axis=-1, keepdims=True)


def _lda(shrinkage: str | float, n_classes: int) -> Any:
    from sklearn.discriminant_analysis import LinearDiscriminantAnalysis

    return LinearDiscriminantAnalysis(
        solver="lsqr", shrinkage=shrinkage, priors=np.full(n_classes, 1.0 / n_classes)
    )


def _fit_lda(shrinkage: str | float, n_classes: int, x: np.ndarray, y: np.ndarray) -> Any:
    with warnings.catch_warnings():
        # a class of one trial has no spread of its own: sklearn warns, the pooled covariance copes
        warnings.simplefilter("ignore", RuntimeWarning)
        warnings.simplefilter("ignore", UserWarning)
        return _lda(shrinkage, n_classes).fit(x, y)


def _multiclass_form(model: Any) -> tuple[np.ndarray, np.ndarray]:
    """(coef (classes, features), intercept (classes,)) of a fitted LDA. With two classes scikit-learn
    keeps one row (the log-odds of the second class); rows [0, w] and intercepts [0, b] give the same
    posterior under a softmax (softmax([0, s]) = [1 - sigmoid(s), sigmoid(s)])."""
    coef = np.atleast_2d(np.asarray(model.coef_, dtype=np.float64))
    intercept = np.atleast_1d(np.asarray(model.intercept_, dtype=np.float64))
    if len(model.classes_) == 2 and coef.shape[0] == 1:
        coef = np.vstack([np.zeros_like(coef), coef])
        intercept = np.concatenate([[0.0], intercept])
    return coef, intercept


def _scores(model: Any, x: np.ndarray) -> np.ndarray:
    """Decision scores (samples, classes), in the multiclass form also for two classes."""
    z = np.asarray(model.decision_function(x), dtype=np.float64)
    return np.column_stack([np.zeros(len(z)), z]) if z.ndim == 1 else z


def _fit_temperature(logits: np.ndarray, y: np.ndarray) -> float:
    """The temperature minimising the cross-validated negative log-likelihood (grid, deterministic)."""
    best_t, best_nll = 1.0, math.inf
    for temp in np.geomspace(0.2, 20.0, 81):
        p = _softmax(logits / temp)
        nll = -float(np.mean(np.log(np.clip(p[np.arange(len(y)), y], 1e-300, None))))
        if nll < best_nll - 1e-12:
            best_t, best_nll = float(temp), nll
    return best_t


def fit_angle_estimator(
    train_by_angle: Mapping[float, pd.DataFrame], params: CuesParams, log: Log | None = None
) -> dict[str, Any]:
    """One LDA per evidence stage on every angle's training trials; temperature by group CV."""
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
    feats: list[list[float]] = []
    labels: list[int] = []
    groups: list[str] = []
    stages: list[int] = []
    for k, a in enumerate(angles):
        for tr in trials_of(train_by_angle[a], channels, a):
            ev = _run_evidence(tr.t, tr.volts, params)
            f = ev.features()
            if f is None:
                continue
            feats.append(f)
            labels.append(k)
            groups.append(tr.batch)
            stages.append(ev.stage)
    n_ch = len(channels)
    y_all, g_all, st_all = np.array(labels), np.array(groups), np.array(stages)
    out_stages = []
    for j in range(len(params.evidence_levels) + 1):
        sel = np.flatnonzero(st_all >= j)
        y = y_all[sel]
        present = np.unique(y)
        if len(present) < len(angles) or len(sel) <= len(angles) + 1:
            log(
                f"angle estimator: stage {j} has too few trials of every angle ({len(sel)}), stages stop here"
            )
            break
        x = np.array([feats[i][: n_ch * (j + 1)] for i in sel])
        model = _fit_lda(params.lda_shrinkage, len(angles), x, y)
        temp, cv_acc = 1.0, None
        g = g_all[sel]
        folds = np.unique(g) if len(np.unique(g)) >= 2 else None
        fold_of = g if folds is not None else (np.arange(len(sel)) % 5).astype(str)
        logits = np.full((len(sel), len(angles)), np.nan)
        for f in np.unique(fold_of):
            tr_m, te_m = fold_of != f, fold_of == f
            if len(np.unique(y[tr_m])) < len(angles):
                continue
            m = _fit_lda(params.lda_shrinkage, len(angles), x[tr_m], y[tr_m])
            logits[te_m] = _scores(m, x[te_m])
        ok = np.isfinite(logits).all(axis=1)
        if ok.any():
            cv_acc = float(np.mean(np.argmax(logits[ok], axis=1) == y[ok]))
            if params.calibrate_temperature:
                temp = _fit_temperature(logits[ok], y[ok])
        coef, intercept = _multiclass_form(model)
        out_stages.append(
            {
                "coef": _siglist(coef),
                "intercept": _siglist(intercept),
                "temperature": _sig(temp),
                "n_train": len(sel),
                "cv_accuracy": None if cv_acc is None else _sig(cv_acc, 4),
            }
        )
        log(
            f"angle estimator: stage {j} ({len(sel)} trials) cross-validated accuracy "
            f"{'n/a' if cv_acc is None else f'{cv_acc:.2f}'}, temperature {temp:.3g}"
        )
    if not out_stages:
        rested = ", ".join(f"{angle_name(a)}° {int(np.sum(y_all == k))}" for k, a in enumerate(angles))
        raise ValueError(
            "cannot fit the angle estimator: it needs training trials with a rest reading at every "
            f"angle, more than {len(angles) + 1} in all (has {rested})"
        )
    return {
        "method": "LDA (lsqr, shrinkage) per evidence stage, uniform priors, softmax(scores / temperature)",
        "features": "rest mean volts per channel, then log(v / rest) per channel when its norm first "
        "reaches each evidence level",
        "classes_deg": angles,
        "levels": [float(x) for x in params.evidence_levels[: len(out_stages) - 1]],
        "stages": out_stages,
        "cv": "leave-one-batch-out" if len(np.unique(g_all)) >= 2 else "5-fold by trial",
    }


def try_fit_angle_estimator(
    train_by_angle: Mapping[float, pd.DataFrame], params: CuesParams, log: Log | None = None
) -> tuple[dict[str, Any] | None, str | None]:
    """(`fit_angle_estimator` result, None), or (None, why it cannot be fitted) with a warning logged:
    the cues then fall back to the paper's profile method."""
    log = log or (lambda _m: None)
    try:
        return fit_angle_estimator(train_by_angle, params, log), None
    except (ValueError, np.linalg.LinAlgError) as e:
        reason = str(e).removeprefix("cannot fit the angle estimator: ")
    log(f"warning: no angle estimator ({reason}): the cues fall back to the paper's profile method")
    return None, reason


def _standard_profile(trials: Sequence[Trial], params: CuesParams) -> tuple[dict[str, Any], list[int]]:
    """Mean and spread of the reference force against time since the detected contact."""
    grid = np.arange(0.0, params.profile_horizon_s + 1e-9, params.profile_dt_s)
    rows, contacts = [], []
    for tr in trials:
        ev = _run_evidence(tr.t, tr.volts, params)
        contacts.append(ev.contact_i)
        if ev.contact_t is None:
            continue
        tt = ev.contact_t + grid
        prof = np.stack([np.interp(tt, tr.t, tr.force[:, k], right=np.nan) for k in range(3)], axis=1)
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
            "axes": list(AXES),
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
    out[contact_i:] = np.sqrt(cum / (3 * np.maximum(cnt, 1)))
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
) -> dict[str, Any]:
    """The cue pack of one preset angle, from training splits only (see the module docstring).

    `train_by_angle`: every angle's training frame (the angle estimator needs them all).
    `predicted`: {kind: {angle: forces}}, the preset angle's model of each kind on every angle's
    training frame (rows in frame order), used to calibrate the paper-method thresholds per kind;
    None calibrates them on the reference force alone (an ideal model).
    `angle_estimator`: a `fit_angle_estimator` result to reuse (it is the same for every preset);
    `estimator_unavailable`: why there is none (then none is fitted). Without either, it is fitted here.

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
    trials = {a: trials_of(train_by_angle[a], channels, a) for a in angles}
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
        contacts = {a: [_run_evidence(tr.t, tr.volts, params).contact_i for tr in trials[a]] for a in angles}
        for kind in [REFERENCE, *predicted]:
            by_cue: dict[str, list[np.ndarray]] = {c: [] for c in VERDICTS}
            for a in angles:
                if kind == REFERENCE:
                    forces = [tr.force for tr in trials[a]]
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
        estimator, estimator_unavailable = try_fit_angle_estimator(train_by_angle, params, log)
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
    }
    if unavailable:
        pack["unavailable"] = dict(sorted(unavailable.items()))
    return pack


def build_packs(
    train_by_angle: Mapping[float, pd.DataFrame],
    predicted_for: Callable[[float], Predicted],
    params: CuesParams,
    log: Log,
) -> dict[float, dict[str, Any]]:
    """The cue pack of every angle with training rows; `predicted_for(preset)` gives that preset's
    models' predictions on every angle's training frame ({kind: {angle: forces}})."""
    estimator, no_estimator = try_fit_angle_estimator(train_by_angle, params, log)
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
        )
        log(f"pack for {angle_name(preset)}° built ({time.perf_counter() - started:.1f} s)")
    return packs


def pack_json(pack: Mapping[str, Any]) -> str:
    """A pack's file text: compact, sorted, strict JSON (what the client's model metadata carries)."""
    return json.dumps(pack, sort_keys=True, separators=(",", ":"), ensure_ascii=False, allow_nan=False) + "\n"
