"""The paper's method, fitted: the preset angle's standard force profile (mean and spread of the
reference force against time since the detected contact) and the thresholds that cut the profile score
(`needlecue_runtime.cues.profile`) into continue / correct / stop, per model kind, on training trials only.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from needlecue_runtime.cues.pack import REFERENCE, VERDICTS, StandardProfile, cue_for_deviation, sig, siglist
from needlecue_runtime.cues.profile import profile_scores
from needlecue_runtime.vocab import AXES
from pipeline.config import CuesParams
from pipeline.cues.trials import Trial, run_evidence
from pipeline.logs import Log

Predicted = Mapping[str, Mapping[float, np.ndarray]]  # {kind: {angle: forces on its training frame}}


def standard_profile(trials: Sequence[Trial], params: CuesParams) -> tuple[dict[str, Any], list[int]]:
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
            "mean_n": siglist(mean, 5),
            "sd_n": siglist(sd, 5),
            "floor_n": float(params.profile_floor_n),
            "n_trials": len(rows),
            "time_origin": "the contact detected from the estimator's volts (as at run time)",
        },
        contacts,
    )


def best_thresholds(scores: Sequence[np.ndarray]) -> tuple[float, float, float]:
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


def paper_thresholds(
    trials: Mapping[float, Sequence[Trial]],
    preset: float,
    profile: Mapping[str, Any],
    predicted: Predicted,
    params: CuesParams,
    log: Log,
) -> tuple[dict[str, Any], dict[str, str]]:
    """({kind: its thresholds}, {"thresholds.profile.<kind>": why none}) of the paper's method at the
    preset angle: per model kind in `predicted` ({kind: {angle: forces}}) and the reference force
    (REFERENCE, an ideal model), the cut points of the profile score (`needlecue_runtime.cues.profile`) that
    best tell the training trials' true cues apart, frame by frame."""
    angles = sorted(trials)
    thresholds: dict[str, Any] = {}
    unavailable: dict[str, str] = {}
    typed = StandardProfile.model_validate(profile)
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
                s = profile_scores(tr.t, f, ci, typed, params.profile_horizon_s)
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
        t1, t2, bal = best_thresholds(
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
            "continue_below": sig(t1),
            "stop_from": sig(t2),
            "train_balanced_accuracy": sig(bal, 4),
        }
        log(
            f"preset {preset:g}°: paper-method thresholds ({kind}) {t1:.3g} / {t2:.3g}, "
            f"per-frame balanced accuracy on training {bal:.2f}"
        )
    return thresholds, unavailable
