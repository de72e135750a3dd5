"""`cues` stage: the simulator's angle cues (the paper's conclusion), and how good they are.

The paper ends with two rules for the simulator: at the preset angle with the force in range,
tell the trainee to *continue*; off the preset angle, tell them to *correct* (about 15° off) or
to *stop* (30° or more), judged from the predicted force profile. Two ways of doing that live here:

- **paper** (profile comparison alone): the preset angle's model predicts the force; a running,
  spread-normalised RMS distance between that prediction and the preset angle's *standard
  profile* (mean ± spread of the reference force against time since contact, over its training
  trials) is mapped to continue / correct / stop by two thresholds. The thresholds are
  calibrated per model kind on the training splits of every angle (the preset model on each
  angle's training trials), maximising the per-frame balanced accuracy.
- **combined** (ours): the estimator's own signal says which angle it is held at. At rest the
  needle's weight presses the tilted tripod differently at each angle (physics.md); once the
  tissue pushes back, the direction in which the three voltages move (log-ratios to the rest
  reading, taken when their norm first reaches each of `evidence_levels`: speed-invariant, and
  mostly before puncture, while the indented surface still pushes across the needle) depends on
  the angle too. One linear discriminant (LDA, shrinkage, uniform priors) per evidence stage,
  fitted on the training splits of all angles, its temperature calibrated by leave-one-batch-out
  cross-validation, gives a posterior over the trained angles; summed into P(on the preset
  angle), P(about 15° off), P(30° or more off) it picks the cue. The paper's profile serves as
  the "force in range" check: a predicted force above `force_margin` × the largest force of the
  preset angle's training trials means stop, whatever the angle.

Both are debounced (a new cue must hold `debounce_s` before it is shown) with hysteresis, and
strictly causal: `CueTracker.update` sees one frame at a time, never a future one.

A *cue pack* (`build_cue_pack`, format "needlecue-cues/1") is a small JSON-able dict shipped with
the preset angle's model: the standard profile, the angle estimator's coefficients, the
thresholds and the params they came from. Everything in it comes from training splits only.

`evaluate_cues` runs, for every preset angle A and every held-out (external) trial of every
true angle B, the preset angle's model and a tracker, and scores the cue against the truth
(|B − A| = 0 → continue, 15 → correct, ≥ 30 → stop): confusion matrices (at the end of the
insertion and per frame during it), accuracy, and the seconds into the insertion until the cue
is right and stays right to the end of the insertion. The insertion's start and end come from
the `phase` column (labelled from the reference force), for scoring only; the tracker never
sees them.

Small or unusual data never stops the pipeline: what cannot be built is left out and said, with
why, in the log (a warning), the packs (`unavailable`: {what: why}), evaluation.json and summary.md.
No angle estimator (one angle only, too few trials, no rest reading): `angle_estimator` is null and
the tracker's cue falls back to the paper method, its reason saying that the angle estimate is
unavailable. No standard profile (no trial with a contact): no paper-method cue at that preset.
No external trials to score (or no model kind with a checkpoint for every preset): evaluation.json
is `{"skipped": why, ...}` and the figures only carry that message. The stage fails only on real
errors: missing input folders, bad params, inconsistent channels.

Usage: `python -m pipeline.cues PROCESSED_DIR MODELS_DIR OUT_DIR [--params params.yaml]`; writes
`packs/<angle>.json`, `evaluation.json`, `confusion.png`, `time_to_cue.png`, `summary.md`.
"""

from __future__ import annotations

import itertools
import json
import math
import sys
import time
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, Protocol

import numpy as np
import pandas as pd
import typer
from pydantic import Field, model_validator

from pipeline.config import Section, load_section
from pipeline.evaluate import angle_name, load_model
from pipeline.models import TARGETS, channels_of

FORMAT = "needlecue-cues/1"
CUES = ("wait", "continue", "correct", "stop")
VERDICTS = CUES[1:]  # the cues a deviation maps to
METHODS = ("combined", "paper")
DEVIATION_GROUPS = ("0", "15", "30", ">=45")
REFERENCE = "reference"  # profile thresholds calibrated on the reference force (no model)
MIN_VOLTS = 1e-3  # floor before taking logs (an unloaded FSR reads a few mV)
PNG_METADATA: dict[str, Any] = {"Software": None}
DIGITS = 4  # evaluation.json precision

Log = Callable[[str], None]


def _stderr(msg: str) -> None:
    print(f"cues: {msg}", file=sys.stderr, flush=True)


class CuesParams(Section):
    """`cues`: the simulator's angle cues (pipeline/cues.py)."""

    kinds: tuple[Literal["ls", "fnn", "lstm"], ...] = Field(("ls", "fnn", "lstm"), min_length=1)
    # deviation bands: |angle - preset| below continue_below_deg -> continue, from stop_from_deg -> stop
    continue_below_deg: float = Field(7.5, gt=0)
    stop_from_deg: float = Field(22.5, gt=0)
    # contact: any channel's |log(v / rest mean)| above contact_threshold for contact_samples frames
    contact_threshold: float = Field(0.02, gt=0)
    contact_samples: int = Field(2, ge=1)
    min_rest_s: float = Field(0.3, ge=0, description="rest reading needed before a contact or a cue")
    # angle estimator: one LDA per evidence stage (rest, then each loading level reached)
    evidence_levels: tuple[float, ...] = (0.05, 0.1, 0.15, 0.2, 0.25, 0.3, 0.35, 0.4, 0.45)
    lda_shrinkage: Literal["auto"] | float = "auto"
    calibrate_temperature: bool = True
    min_stage: int = Field(0, ge=0, description="evidence stage needed to leave wait (0: rest reading)")
    min_confidence: float = Field(0.7, ge=0, le=1)
    switch_margin: float = Field(0.1, ge=0, le=1)
    debounce_s: float = Field(0.2, ge=0)
    # the paper's standard profile and its comparison
    profile_dt_s: float = Field(0.1, gt=0)
    profile_horizon_s: float = Field(10.0, gt=0)
    profile_floor_n: float = Field(0.05, gt=0, description="added in quadrature to the profile's spread")
    min_profile_s: float = Field(1.0, ge=0, description="seconds after contact before the profile cues")
    profile_hysteresis: float = Field(0.05, ge=0, lt=1)
    # force in range (combined method)
    force_check: bool = True
    force_margin: float = Field(1.5, gt=0)

    @model_validator(mode="after")
    def _check(self) -> CuesParams:
        if self.stop_from_deg <= self.continue_below_deg:
            raise ValueError("stop_from_deg must exceed continue_below_deg")
        lv = self.evidence_levels
        if any(x <= 0 for x in lv) or any(b <= a for a, b in itertools.pairwise(lv)):
            raise ValueError(f"evidence_levels must be positive and increasing, got {list(lv)}")
        if isinstance(self.lda_shrinkage, float) and not 0 <= self.lda_shrinkage <= 1:
            raise ValueError("lda_shrinkage is 'auto' or a float in [0, 1]")
        if self.min_stage > len(lv):
            raise ValueError(f"min_stage {self.min_stage} exceeds the {len(lv)} evidence levels")
        return self


def cue_for_deviation(dev_deg: float, continue_below: float = 7.5, stop_from: float = 22.5) -> str:
    """continue / correct / stop for an absolute angle deviation in degrees."""
    d = abs(dev_deg)
    return "continue" if d < continue_below else ("correct" if d < stop_from else "stop")


def deviation_group(dev_deg: float) -> str:
    d = round(abs(dev_deg), 6)
    return "0" if d == 0 else "15" if d == 15 else "30" if d == 30 else ">=45"


def _sig(x: float, digits: int = 6) -> float:
    """A float rounded to `digits` significant digits (small, stable JSON)."""
    return float(f"{float(x):.{digits}g}") + 0.0


def _siglist(a: Any, digits: int = 6) -> Any:
    arr = np.asarray(a, dtype=np.float64)
    if arr.ndim == 0:
        return _sig(float(arr), digits)
    return [_siglist(x, digits) for x in arr]


def _floats(x: Any) -> list[float]:
    return x.tolist() if isinstance(x, np.ndarray) else [float(v) for v in x]


# ---------------------------------------------------------------------------------------------
# Causal evidence: rest reading, contact, loading snapshots (shared by build and tracker)
# ---------------------------------------------------------------------------------------------


class _Evidence:
    """What the estimator's volts say so far. `push` one frame at a time; True if the features
    changed (the rest mean moved, or a new loading level was reached)."""

    __slots__ = (
        "contact_i",
        "contact_t",
        "levels",
        "min_rest_s",
        "n_ch",
        "n_confirm",
        "pending",
        "rest",
        "rest_n",
        "rest_sum",
        "snaps",
        "t_first",
        "thr",
    )

    def __init__(self, n_ch: int, levels: Sequence[float], thr: float, n_confirm: int, min_rest_s: float):
        self.n_ch, self.levels, self.thr = n_ch, tuple(levels), thr
        self.n_confirm, self.min_rest_s = n_confirm, min_rest_s
        self.reset()

    def reset(self) -> None:
        self.rest_sum = [0.0] * self.n_ch
        self.rest_n = 0
        self.t_first: float | None = None
        self.pending: list[tuple[float, list[float], Any]] = []
        self.contact_t: float | None = None
        self.contact_i = -1  # frame index of contact (counted from reset)
        self.rest: list[float] | None = None  # rest mean, frozen at contact
        self.snaps: list[list[float]] = []

    @property
    def stage(self) -> int:
        return len(self.snaps)

    def rest_mean(self) -> list[float] | None:
        if self.rest is not None:
            return self.rest
        if self.rest_n == 0:
            return None
        n = self.rest_n
        return [s / n for s in self.rest_sum]

    def rest_ready(self, t: float) -> bool:
        return self.contact_t is not None or (
            self.t_first is not None and t - self.t_first >= self.min_rest_s - 1e-9 and self.rest_n > 0
        )

    def features(self) -> list[float] | None:
        rest = self.rest_mean()
        if rest is None:
            return None
        out = list(rest)
        for s in self.snaps:
            out.extend(s)
        return out

    def push(self, t: float, v: list[float], extra: Any = None, i: int = -1) -> tuple[bool, list]:
        """Feed one frame. Returns (features changed, frames that became post-contact now: the
        confirming run, [(t, v, extra)], empty unless contact was just confirmed or already on)."""
        v = [x if x > MIN_VOLTS else MIN_VOLTS for x in v]
        if self.contact_t is not None:
            return self._snap(v), [(t, v, extra)]
        if self.t_first is None:
            self.t_first = t
        if not self.rest_ready(t):
            self._add_rest(v)
            return True, []
        n = self.rest_n
        dev = max(abs(math.log(x * n / s)) for x, s in zip(v, self.rest_sum, strict=True))
        if dev > self.thr:
            self.pending.append((t, v, extra, i))
            if len(self.pending) < self.n_confirm:
                return False, []
            self.rest = [s / n for s in self.rest_sum]
            self.contact_t, self.contact_i = self.pending[0][0], self.pending[0][3]
            changed = False
            run = []
            for tp, vp, ep, _ in self.pending:
                changed |= self._snap(vp)
                run.append((tp, vp, ep))
            self.pending = []
            return changed, run
        for _, vp, _, _ in self.pending:  # the run broke: those were rest after all
            self._add_rest(vp)
        self.pending = []
        self._add_rest(v)
        return True, []

    def _add_rest(self, v: list[float]) -> None:
        rs = self.rest_sum
        for k, x in enumerate(v):
            rs[k] += x
        self.rest_n += 1

    def _snap(self, v: list[float]) -> bool:
        if len(self.snaps) >= len(self.levels):
            return False
        s = [math.log(x / r) for x, r in zip(v, self.rest, strict=True)]  # type: ignore[arg-type]
        norm = math.sqrt(sum(x * x for x in s))
        changed = False
        while len(self.snaps) < len(self.levels) and norm >= self.levels[len(self.snaps)]:
            self.snaps.append(s)
            changed = True
        return changed


def _run_evidence(t: np.ndarray, volts: np.ndarray, params: CuesParams) -> _Evidence:
    """The evidence of a whole trial (causal code, fed frame by frame until every level is reached)."""
    ev = _Evidence(
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


# ---------------------------------------------------------------------------------------------
# Building a cue pack
# ---------------------------------------------------------------------------------------------


class Predictor(Protocol):
    kind: str

    def predict(self, frame: pd.DataFrame) -> np.ndarray: ...


@dataclass
class _Trial:
    angle: float
    batch: str
    t: np.ndarray  # (n,)
    volts: np.ndarray  # (n, channels)
    force: np.ndarray  # (n, 3) reference
    ins_start: int  # from the phase labels (-1 if none)
    ins_end: int
    rows: np.ndarray  # row positions in the source frame, time order


def _trials_of(frame: pd.DataFrame, channels: Sequence[str], angle: float) -> list[_Trial]:
    out = []
    if frame.empty:
        return out
    keys = [c for c in ("batch_id", "trial_id") if c in frame.columns]
    groups = frame.groupby(keys, sort=True).indices if keys else {("",): np.arange(len(frame))}
    t_all = frame["t_s"].to_numpy(np.float64)
    v_all = frame[list(channels)].to_numpy(np.float64)
    f_all = frame[list(TARGETS)].to_numpy(np.float64) if set(TARGETS) <= set(frame.columns) else None
    ph_all = frame["phase"].to_numpy() if "phase" in frame.columns else None
    for key, idx in groups.items():
        idx = np.asarray(idx)
        idx = idx[np.argsort(t_all[idx], kind="stable")]
        if ph_all is not None:
            ins = np.flatnonzero(ph_all[idx] == "insertion")
            s, e = (int(ins[0]), int(ins[-1])) if len(ins) else (-1, -1)
        else:
            s = e = -1
        batch = str(key[0]) if isinstance(key, tuple) else str(key)
        force = f_all[idx] if f_all is not None else np.full((len(idx), 3), np.nan)
        out.append(_Trial(angle, batch, t_all[idx], v_all[idx], force, s, e, idx))
    return out


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
        for tr in _trials_of(train_by_angle[a], channels, a):
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


def _standard_profile(trials: Sequence[_Trial], params: CuesParams) -> tuple[dict[str, Any], list[int]]:
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
            "axes": list(TARGETS),
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
    predictor: Predictor | Mapping[str, Predictor] | None = None,
    log: Log | None = None,
    angle_estimator: Mapping[str, Any] | None = None,
    *,
    estimator_unavailable: str | None = None,
) -> dict[str, Any]:
    """The cue pack of one preset angle, from training splits only (see the module docstring).

    `train_by_angle`: every angle's training frame (the angle estimator needs them all).
    `predictor`: the preset angle's model (or {kind: model}) used to calibrate the paper-method
    thresholds per kind; None calibrates them on the reference force alone (an ideal model).
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
    trials = {a: _trials_of(train_by_angle[a], channels, a) for a in angles}
    rate = _rate_hz(trials[preset])
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

    predictors: dict[str, Predictor] = {}
    if isinstance(predictor, Mapping):
        predictors = dict(predictor)
    elif predictor is not None:
        predictors = {str(predictor.kind): predictor}
    thresholds: dict[str, Any] = {}
    if profile is not None:
        mean = np.asarray(profile["mean_n"])
        sde = np.sqrt(np.asarray(profile["sd_n"]) ** 2 + params.profile_floor_n**2)
        contacts = {a: [_run_evidence(tr.t, tr.volts, params).contact_i for tr in trials[a]] for a in angles}
        for kind in [REFERENCE, *predictors]:
            by_cue: dict[str, list[np.ndarray]] = {c: [] for c in VERDICTS}
            for a in angles:
                frame = train_by_angle[a]
                if kind == REFERENCE:
                    forces = [tr.force for tr in trials[a]]
                else:
                    pred = np.asarray(
                        predictors[kind].predict(frame.drop(columns=list(TARGETS))), dtype=float
                    )
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


def _rate_hz(trials: Sequence[_Trial]) -> float:
    dts = np.concatenate([np.diff(tr.t) for tr in trials if len(tr.t) > 1] or [np.zeros(0)])
    dts = dts[dts > 0]
    return float(1.0 / np.median(dts)) if len(dts) else math.nan


# ---------------------------------------------------------------------------------------------
# The tracker
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class CueState:
    cue: str  # "wait" | "continue" | "correct" | "stop"
    angle_est_deg: float | None
    reason: str


class _Debounce:
    """A new candidate cue is shown once it has been the candidate for `hold_s` seconds."""

    __slots__ = ("hold", "pending", "shown", "since")

    def __init__(self, hold_s: float) -> None:
        self.hold = hold_s - 1e-9
        self.reset()

    def reset(self) -> None:
        self.shown, self.pending, self.since = 0, -1, 0.0

    def step(self, t: float, candidate: int) -> int:
        if candidate == self.shown:
            self.pending = -1
        elif candidate != self.pending:
            self.pending, self.since = candidate, t
        if self.pending >= 0 and t - self.since >= self.hold:
            self.shown, self.pending = self.pending, -1
        return self.shown


def check_pack(pack: Mapping[str, Any]) -> None:
    if not isinstance(pack, Mapping) or pack.get("format") != FORMAT:
        got = pack.get("format") if isinstance(pack, Mapping) else type(pack).__name__
        raise ValueError(f"not a {FORMAT} cue pack (format {got!r})")
    for key in (
        "preset_angle_deg",
        "channels",
        "standard_profile",
        "angle_estimator",
        "thresholds",
        "params",
    ):
        if key not in pack:
            raise ValueError(f"the cue pack lacks {key!r}")


class CueTracker:
    """Frame-by-frame cues for one insertion at one preset angle (strictly causal).

    `method`: "combined" (angle estimate + force-in-range check, the default) or "paper"
    (profile comparison alone). Both are computed every frame; `update` returns the chosen one
    and `states` holds both. `model_kind` picks the paper-method thresholds calibrated for that
    model ("ls", "fnn", "lstm"; default: the first of the pack's `kinds` it has thresholds for, else
    those calibrated on the reference force).
    Call `reset()` at the start of every insertion, with the needle at rest.

    A pack without an angle estimator (`angle_estimator` null: see `unavailable` in the pack) falls
    back to the paper method for the "combined" cue too, its reason saying that the angle estimate is
    unavailable; a pack without a standard profile or profile thresholds has no paper-method cue (it
    stays on "wait", saying why). `angle_unavailable` / `profile_unavailable` hold those reasons.
    """

    def __init__(
        self,
        pack: Mapping[str, Any],
        preset_angle_deg: float,
        *,
        model_kind: str | None = None,
        method: str = "combined",
    ) -> None:
        check_pack(pack)
        if abs(float(pack["preset_angle_deg"]) - float(preset_angle_deg)) > 1e-6:
            raise ValueError(
                f"this cue pack is for the preset angle {pack['preset_angle_deg']:g}°, "
                f"not {preset_angle_deg:g}°"
            )
        if method not in METHODS:
            raise ValueError(f"method must be one of {METHODS}, got {method!r}")
        self.method = method
        self.preset = float(preset_angle_deg)
        p = CuesParams.model_validate(pack["params"])
        self.params = p
        missing = pack.get("unavailable") or {}
        est = pack["angle_estimator"]
        if est is not None and not est.get("stages"):
            est = None
        self.angle_unavailable: str | None = None
        if est is None:
            self.angle_unavailable = "angle estimate unavailable: " + str(
                missing.get("angle_estimator", "the cue pack has no angle estimator")
            )
        self.classes = np.asarray(est["classes_deg"] if est else [], dtype=np.float64)
        self._classes = [float(a) for a in self.classes]
        stages = est["stages"] if est else []
        self._w = [np.asarray(s["coef"], dtype=np.float64) for s in stages]
        self._b = [np.asarray(s["intercept"], dtype=np.float64) for s in stages]
        self._temp = [float(s["temperature"]) for s in stages]
        levels = est["levels"] if est else []
        th = pack["thresholds"]
        devcls = [
            VERDICTS.index(cue_for_deviation(a - self.preset, th["continue_below_deg"], th["stop_from_deg"]))
            for a in self._classes
        ]
        self._to_dev = np.zeros((len(self._classes), 3))
        self._to_dev[np.arange(len(self._classes)), devcls] = 1.0
        prof = pack["standard_profile"] or {"mean_n": [], "sd_n": [], "floor_n": 1.0, "dt_s": 1.0}
        self._mean = [tuple(r) for r in prof["mean_n"]]
        floor2 = float(prof["floor_n"]) ** 2
        self._isd = [tuple(1.0 / math.sqrt(s * s + floor2) for s in r) for r in prof["sd_n"]]
        self._dt = float(prof["dt_s"])
        self._n_prof = len(self._mean)
        self._horizon = p.profile_horizon_s + 1e-9
        kinds = th["profile"] or {}
        self.profile_unavailable: str | None = None
        if model_kind is None:
            model_kind = next((k for k in p.kinds if k in kinds), REFERENCE)  # not dict order: JSON sorts
        if not self._n_prof:
            self.profile_unavailable = "standard profile unavailable: " + str(
                missing.get("standard_profile", "the cue pack has none")
            )
        elif not kinds:
            self.profile_unavailable = "profile thresholds unavailable: " + str(
                missing.get(f"thresholds.profile.{model_kind}", "the cue pack has none")
            )
        elif model_kind not in kinds:
            raise ValueError(
                f"the cue pack has no profile thresholds for {model_kind!r} (has {sorted(kinds)})"
            )
        self.model_kind = model_kind
        self._t1 = float(kinds[model_kind]["continue_below"]) if model_kind in kinds else math.inf
        self._t2 = float(kinds[model_kind]["stop_from"]) if model_kind in kinds else math.inf
        limit = th.get("force_limit_n")
        self._force_limit2 = float(limit) ** 2 if p.force_check and limit is not None else math.inf
        self._ev = _Evidence(
            len(pack["channels"]), levels, p.contact_threshold, p.contact_samples, p.min_rest_s
        )
        self._min_stage = min(p.min_stage, len(levels))
        self._deb = _Debounce(p.debounce_s)
        self._deb_paper = _Debounce(p.debounce_s)
        self.reset()

    def reset(self) -> None:
        self._ev.reset()
        self._deb.reset()
        self._deb_paper.reset()
        self._pdev: list[float] | None = None
        self._map = -1
        self._z2, self._nz = 0.0, 0
        self._score: float | None = None
        self._alarm = False
        self._state_key: tuple = ()
        self._paper_key: tuple = ()
        self.states: dict[str, CueState] = {
            m: CueState("wait", None, "reset: waiting for a rest reading") for m in METHODS
        }

    # -- evidence ----------------------------------------------------------------------------
    @property
    def stage(self) -> int:
        return self._ev.stage

    @property
    def contact_t(self) -> float | None:
        return self._ev.contact_t

    @property
    def force_alarm(self) -> bool:
        """The last frame's predicted force was above the pack's force limit."""
        return self._alarm

    @property
    def profile_score(self) -> float | None:
        return self._score

    def posterior(self) -> np.ndarray | None:
        """P(angle) over the pack's trained angles from the evidence so far (None before rest)."""
        x = self._ev.features()
        if x is None or not self._w:
            return None
        j = min(self._ev.stage, len(self._w) - 1)
        z = (self._w[j] @ np.asarray(x[: self._w[j].shape[1]])) + self._b[j]
        z = z / self._temp[j]
        e = np.exp(z - z.max())
        return e / e.sum()

    def _accumulate(self, t: float, f: Any) -> None:
        tau = t - self._ev.contact_t  # type: ignore[operator]
        if tau > self._horizon:
            return
        g = int(tau / self._dt + 0.5)
        if g >= self._n_prof:
            g = self._n_prof - 1
        m, s = self._mean[g], self._isd[g]
        a, b, c = (f[0] - m[0]) * s[0], (f[1] - m[1]) * s[1], (f[2] - m[2]) * s[2]
        self._z2 += a * a + b * b + c * c
        self._nz += 1

    # -- one frame ---------------------------------------------------------------------------
    def update(self, t_s: float, volts: np.ndarray, force_n: np.ndarray) -> CueState:
        """Feed one frame (volts in the pack's channel order, the model's predicted force in N)."""
        t = float(t_s)
        f = _floats(force_n)
        ev = self._ev
        changed, post = ev.push(t, _floats(volts), f)
        if self._n_prof:
            for tp, _, fp in post:
                self._accumulate(tp, fp)
        if self._nz:
            self._score = math.sqrt(self._z2 / (3 * self._nz))
        if changed and ev.rest_n and self._w:
            p = self.posterior()
            pd_ = (p @ self._to_dev).tolist()  # type: ignore[operator]
            self._pdev = pd_
            self._map = int(np.argmax(p))  # type: ignore[arg-type]
        self._alarm = f[0] * f[0] + f[1] * f[1] + f[2] * f[2] > self._force_limit2

        # combined: angle estimate -> deviation class, force-in-range check
        if self.angle_unavailable is None:
            deb = self._deb
            shown = deb.shown
            cand = shown
            if self._alarm:
                cand = 3
            elif self._pdev is not None and ev.rest_ready(t) and ev.stage >= self._min_stage:
                pdv = self._pdev
                best = 0 if pdv[0] >= pdv[1] and pdv[0] >= pdv[2] else (1 if pdv[1] >= pdv[2] else 2)
                pb = pdv[best]
                if pb >= self.params.min_confidence and (
                    shown == 0 or best + 1 == shown or pb >= pdv[shown - 1] + self.params.switch_margin
                ):
                    cand = best + 1
            cue = deb.step(t, cand)
            key = (cue, self._map, ev.stage, self._alarm, ev.contact_t is not None)
            if key != self._state_key:
                self._state_key = key
                self.states["combined"] = self._combined_state(cue)

        # paper: profile distance -> thresholds (with hysteresis)
        dp = self._deb_paper
        pc = dp.shown
        if (
            self._score is not None
            and self.profile_unavailable is None
            and t - ev.contact_t >= self.params.min_profile_s - 1e-9  # type: ignore[operator]
        ):
            h = self.params.profile_hysteresis
            t1 = self._t1 * (1 + h if pc == 1 else 1 - h if pc == 2 else 1)
            t2 = self._t2 * (1 + h if pc == 2 else 1 - h if pc == 3 else 1)
            s = self._score
            pc = 1 if s < t1 else (2 if s < t2 else 3)
        pcue = dp.step(t, pc)
        pkey = (pcue, ev.contact_t is not None)
        if pkey != self._paper_key:
            self._paper_key = pkey
            self.states["paper"] = self._paper_state(pcue)
            if self.angle_unavailable is not None:  # the combined cue falls back to the paper's
                paper = self.states["paper"]
                self.states["combined"] = CueState(
                    paper.cue, None, f"{self.angle_unavailable}; paper method: {paper.reason}"
                )
        return self.states[self.method]

    def _combined_state(self, cue: int) -> CueState:
        ev = self._ev
        est = self._classes[self._map] if self._map >= 0 else None
        evidence = "rest reading" + (f" + {ev.stage} loading level(s)" if ev.stage else "")
        if cue == 0:
            if not ev.rest_ready(math.inf) or self._pdev is None:
                why = "collecting the rest reading"
            else:
                why = f"not confident yet ({evidence}, best P={max(self._pdev):.2f})"
            return CueState("wait", est, why)
        if self._alarm and cue == 3:
            return CueState("stop", est, "predicted force above the preset angle's range")
        dev = abs(est - self.preset) if est is not None else math.nan
        what = {
            1: "on the preset angle",
            2: "off the preset angle: correct it",
            3: "far off the preset angle: stop",
        }[cue]
        p = self._pdev[cue - 1] if self._pdev is not None else math.nan
        return CueState(
            CUES[cue],
            est,
            f"angle ≈ {est:g}° ({dev:g}° from {self.preset:g}°, P={p:.2f}) from {evidence}: {what}",
        )

    def _paper_state(self, cue: int) -> CueState:
        if cue == 0:
            why = "waiting for contact" if self._ev.contact_t is None else "comparing the profile"
            if self.profile_unavailable is not None:
                why = f"no cue: {self.profile_unavailable}"
            return CueState("wait", None, why)
        return CueState(
            CUES[cue],
            None,
            f"predicted force vs the standard profile of {self.preset:g}°: "
            f"{['', 'within', 'off', 'far off'][cue]} its range",
        )


# ---------------------------------------------------------------------------------------------
# Evaluation
# ---------------------------------------------------------------------------------------------


@dataclass
class Run:
    """One tracker run on one trial: the shown cue per frame (codes into CUES)."""

    kind: str
    method: str
    preset: float
    true_angle: float
    t: np.ndarray
    codes: np.ndarray
    ins_start: int
    ins_end: int
    angle_est: float | None = None
    alarm: bool = False


def _pct(values: Sequence[float], q: float) -> float | None:
    return float(np.percentile(values, q)) if len(values) else None


def time_to_cue(t: np.ndarray, right: np.ndarray, start: int, end: int) -> float | None:
    """Seconds from frame `start` until the cue is right and stays right through frame `end`
    (0 if right throughout; None if wrong at `end`)."""
    ok = right[start : end + 1]
    if not len(ok) or not ok[-1]:
        return None
    wrong = np.flatnonzero(~ok)
    return 0.0 if not len(wrong) else float(t[start + wrong[-1] + 1] - t[start])


def summarise_runs(
    runs: Sequence[Run], continue_below: float = 7.5, stop_from: float = 22.5
) -> dict[str, Any]:
    """Confusion matrices, accuracy and time to cue of tracker runs, per (kind, method)."""
    out: dict[str, Any] = {}
    for run in runs:
        true = VERDICTS.index(cue_for_deviation(run.true_angle - run.preset, continue_below, stop_from)) + 1
        d = out.setdefault(run.kind, {}).setdefault(
            run.method,
            {
                "final": np.zeros((3, 4), dtype=np.int64),
                "frames": np.zeros((3, 4), dtype=np.int64),
                "ttc": {g: [] for g in DEVIATION_GROUPS},
                "n": {g: 0 for g in DEVIATION_GROUPS},
                "right_final": {g: 0 for g in DEVIATION_GROUPS},
                "alarms": 0,
            },
        )
        seg = run.codes[run.ins_start : run.ins_end + 1]
        d["final"][true - 1, run.codes[run.ins_end]] += 1
        d["frames"][true - 1] += np.bincount(seg, minlength=4)
        g = deviation_group(run.true_angle - run.preset)
        d["n"][g] += 1
        d["right_final"][g] += int(run.codes[run.ins_end] == true)
        d["alarms"] += int(run.alarm)
        ttc = time_to_cue(run.t, run.codes == true, run.ins_start, run.ins_end)
        d["ttc"][g].append(ttc)
    result: dict[str, Any] = {}
    for kind, methods in out.items():
        for method, d in methods.items():
            fin, frm = d["final"], d["frames"]
            ttc = {}
            for g in DEVIATION_GROUPS:
                vals = [v for v in d["ttc"][g] if v is not None]
                ttc[g] = {
                    "trials": d["n"][g],
                    "right_at_end": d["right_final"][g],
                    "never_right": d["n"][g] - len(vals),
                    "median_s": _pct(vals, 50),
                    "p90_s": _pct(vals, 90),
                    "seconds": sorted(vals),
                }
            per_class = {
                c: (float(fin[i, i + 1] / fin[i].sum()) if fin[i].sum() else None)
                for i, c in enumerate(VERDICTS)
            }
            result.setdefault(kind, {})[method] = {
                "confusion_final": {
                    "rows_true": list(VERDICTS),
                    "cols_cue": list(CUES),
                    "counts": fin.tolist(),
                },
                "confusion_frames": {
                    "rows_true": list(VERDICTS),
                    "cols_cue": list(CUES),
                    "counts": frm.tolist(),
                },
                "accuracy_final": float(np.trace(fin[:, 1:]) / fin.sum()) if fin.sum() else None,
                "accuracy_frames": float(np.trace(frm[:, 1:]) / frm.sum()) if frm.sum() else None,
                "recall_final": per_class,
                "time_to_cue": ttc,
                "force_alarm_trials": d["alarms"] if method == "combined" else None,
            }
    return result


def read_split(processed_dir: Path, split: str) -> dict[float, pd.DataFrame]:
    """{angle: frame} of one split over the angle folders of `processed_dir` that have it."""
    if not processed_dir.is_dir():
        raise FileNotFoundError(f"{processed_dir}: no such folder (run the split stage first)")
    out = {}
    for folder in processed_dir.iterdir():
        path = folder / f"{split}.parquet"
        if not path.is_file():
            continue
        try:
            angle = float(folder.name)
        except ValueError:
            continue
        out[angle] = pd.read_parquet(path)
    return dict(sorted(out.items()))


def evaluate_cues(
    processed_dir: Path,
    models_dir: Path,
    params: CuesParams,
    packs: Mapping[float, Mapping[str, Any]],
    *,
    loader: Callable[[Path], Predictor] | None = None,
    log: Log = _stderr,
) -> dict[str, Any]:
    """Cue quality on the external trials of every angle, for every preset angle with a pack.

    Without external trials with an insertion phase there is nothing to score: the result is
    `skipped_evaluation(reason)`. The combined method is scored only with an angle estimator."""
    loader = loader or load_model
    external = {a: f for a, f in read_split(Path(processed_dir), "external").items() if len(f)}
    if not external:
        return skipped_evaluation("no external trials (no <angle>/external.parquet with rows)", packs, params)
    if not packs:
        return skipped_evaluation("no cue pack", packs, params)
    first = next(iter(packs.values()))
    channels = list(first["channels"])
    trials: dict[float, list[_Trial]] = {}
    for a, f in external.items():
        missing = [c for c in channels if c not in f.columns]
        if missing:
            raise ValueError(f"{processed_dir}/{angle_name(a)}/external.parquet lacks channel(s) {missing}")
        keep = [tr for tr in _trials_of(f, channels, a) if tr.ins_start >= 0]
        if len(keep) < f.groupby(["batch_id", "trial_id"]).ngroups:
            log(f"warning: {angle_name(a)}°: trials without an insertion phase skipped")
        trials[a] = keep
    if not any(trials.values()):
        return skipped_evaluation(
            "no external trial has frames labelled 'insertion' (nothing to score)", packs, params
        )
    with_estimator = all(p.get("angle_estimator") for p in packs.values())
    runs: list[Run] = []
    angle_conf: dict[tuple[float, float], int] = {}
    clock = [0, 0.0]  # tracker updates, seconds spent in them (log only)

    def track(
        kind: str,
        preset: float,
        pack: Mapping[str, Any],
        methods: Sequence[str],
        force_of: Callable[[_Trial], np.ndarray],
        a: float,
    ) -> None:
        for tr in trials[a]:
            f = force_of(tr)
            tracker = CueTracker(
                pack, preset, model_kind=kind if kind in pack["thresholds"]["profile"] else None
            )
            n = tr.ins_end + 1
            codes = {m: np.zeros(n, dtype=np.int64) for m in METHODS}
            alarm = False
            t0 = time.perf_counter()
            for i in range(n):
                tracker.update(tr.t[i], tr.volts[i], f[i])
                st = tracker.states
                codes["combined"][i] = CUES.index(st["combined"].cue)
                codes["paper"][i] = CUES.index(st["paper"].cue)
                alarm |= tracker.force_alarm
            clock[1] += time.perf_counter() - t0
            clock[0] += n
            est = tracker.states["combined"].angle_est_deg
            for m in methods:
                if m == "combined" and not with_estimator:
                    continue
                runs.append(
                    Run(
                        kind,
                        m,
                        preset,
                        a,
                        tr.t,
                        codes[m],
                        tr.ins_start,
                        tr.ins_end,
                        est if m == "combined" else None,
                        alarm and m == "combined",
                    )
                )
            if kind == REFERENCE and preset == min(packs) and with_estimator:
                key = (a, est if est is not None else math.nan)
                angle_conf[key] = angle_conf.get(key, 0) + 1

    for preset, pack in sorted(packs.items()):
        # the paper's comparison on the measured force: not deployable, its upper bound
        for a in external:
            track(REFERENCE, preset, pack, ("paper",), lambda tr: tr.force, a)
    for kind in params.kinds:
        for preset, pack in sorted(packs.items()):
            model_dir = Path(models_dir) / kind / angle_name(preset)
            if not (model_dir / "model.pt").is_file() and loader is load_model:
                log(f"warning: no {model_dir / 'model.pt'}, {kind} at {angle_name(preset)}° skipped")
                continue
            started = time.perf_counter()
            pred = loader(model_dir)
            for a, frame in external.items():
                forces = np.asarray(
                    pred.predict(frame.drop(columns=[c for c in TARGETS if c in frame])), dtype=float
                )
                track(kind, preset, pack, METHODS, lambda tr, forces=forces: forces[tr.rows], a)
            log(
                f"{kind} at {angle_name(preset)}°: {sum(len(v) for v in trials.values())} trials "
                f"({time.perf_counter() - started:.1f} s)"
            )
    if clock[0]:
        log(
            f"{clock[0]} tracker updates, {1e6 * clock[1] / clock[0]:.1f} µs each on average "
            "(including the evaluation loop)"
        )
    summary = summarise_runs(runs, params.continue_below_deg, params.stop_from_deg)
    classes = sorted(external)
    out = {
        "format": "needlecue-cues-eval/1",
        "kinds": [k for k in params.kinds if k in summary],
        "reference": "results.reference.paper: the profile comparison on the measured reference force "
        "instead of a model's prediction (not deployable: the upper bound of the paper's method)",
        "presets_deg": sorted(float(a) for a in packs),
        "true_angles_deg": classes,
        "external_trials": {angle_name(a): len(trials[a]) for a in classes},
        "truth": f"|true - preset| < {params.continue_below_deg:g}° continue, < {params.stop_from_deg:g}° "
        "correct, else stop; scored from the first to the last frame labelled 'insertion'",
        "angle_estimate_at_insertion_end": _angle_matrix(classes, packs, angle_conf)
        if with_estimator
        else None,
        "results": summary,
    }
    unavailable = _unavailable(packs)
    if unavailable:
        out["unavailable"] = unavailable
    return out


def _angle_matrix(
    classes: Sequence[float], packs: Mapping[float, Mapping[str, Any]], angle_conf: Mapping[tuple, int]
) -> dict[str, Any]:
    est_classes = sorted({float(c) for p in packs.values() for c in p["angle_estimator"]["classes_deg"]})
    angle_matrix = [[angle_conf.get((a, e), 0) for e in est_classes] for a in classes]
    return {
        "rows_true_deg": list(classes),
        "cols_estimated_deg": est_classes,
        "counts": angle_matrix,
        "exact": _ratio(
            sum(
                angle_matrix[i][j] for i, a in enumerate(classes) for j, e in enumerate(est_classes) if a == e
            ),
            angle_matrix,
        ),
        "within_15": _ratio(
            sum(
                angle_matrix[i][j]
                for i, a in enumerate(classes)
                for j, e in enumerate(est_classes)
                if abs(a - e) <= 15 + 1e-9
            ),
            angle_matrix,
        ),
    }


def _unavailable(packs: Mapping[float, Mapping[str, Any]]) -> dict[str, dict[str, str]]:
    """{preset angle: {what: why}} over the packs that lack something."""
    return {angle_name(a): dict(p["unavailable"]) for a, p in sorted(packs.items()) if p.get("unavailable")}


def skipped_evaluation(
    reason: str, packs: Mapping[float, Mapping[str, Any]], params: CuesParams
) -> dict[str, Any]:
    """The evaluation.json of a stage that could not score the cues, saying why."""
    out: dict[str, Any] = {
        "format": "needlecue-cues-eval/1",
        "skipped": reason,
        "kinds": [],
        "presets_deg": sorted(float(a) for a in packs),
        "model_kinds_asked": list(params.kinds),
        "results": {},
    }
    unavailable = _unavailable(packs)
    if unavailable:
        out["unavailable"] = unavailable
    return out


def _ratio(num: int, matrix: list[list[int]]) -> float | None:
    total = sum(map(sum, matrix))
    return num / total if total else None


# ---------------------------------------------------------------------------------------------
# Outputs
# ---------------------------------------------------------------------------------------------


def _round(obj: Any) -> Any:
    if isinstance(obj, float):
        return None if not math.isfinite(obj) else round(obj, DIGITS) + 0.0
    if isinstance(obj, dict):
        return {str(k): _round(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_round(v) for v in obj]
    if isinstance(obj, np.generic):
        return _round(obj.item())
    return obj


def dump_json(obj: Any) -> str:
    return json.dumps(_round(obj), indent=1, sort_keys=True, ensure_ascii=False) + "\n"


def _label(method: str) -> str:
    return {"combined": "angle estimate + force check (ours)", "paper": "profile comparison (paper)"}[method]


def _no_results(evaluation: Mapping[str, Any]) -> str | None:
    """Why there is nothing to plot (None if there is)."""
    res = evaluation.get("results") or {}
    if evaluation.get("skipped"):
        return f"Cue evaluation skipped: {evaluation['skipped']}"
    if not [k for k in evaluation.get("kinds", []) if k in res]:
        return "No model's cues were scored"
    return None


def _placeholder(message: str, path: Path) -> None:
    """A small figure that only says why there is no plot (deterministic bytes)."""
    import textwrap

    from matplotlib.figure import Figure

    fig = Figure(figsize=(6, 2))
    fig.text(0.5, 0.5, textwrap.fill(message, 70), ha="center", va="center", fontsize=9, wrap=True)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100, metadata=PNG_METADATA)


def plot_confusion(evaluation: Mapping[str, Any], path: Path) -> None:
    from matplotlib.figure import Figure

    if (why := _no_results(evaluation)) is not None:
        _placeholder(why, path)
        return
    res = evaluation["results"]
    kinds = [k for k in evaluation["kinds"] if k in res]
    methods = [m for m in METHODS if any(m in res[k] for k in kinds)]
    rows = max(len(kinds), 1)
    fig = Figure(figsize=(5 * len(methods), 3.2 * rows))
    axes = fig.subplots(rows, len(methods), squeeze=False)
    for r, kind in enumerate(kinds):
        for c, method in enumerate(methods):
            if method not in res[kind]:
                axes[r][c].set_axis_off()
                continue
            ax = axes[r][c]
            m = np.asarray(res[kind][method]["confusion_final"]["counts"])
            share = m / np.maximum(m.sum(axis=1, keepdims=True), 1)
            ax.imshow(share, cmap="Blues", vmin=0, vmax=1, aspect="auto")
            for i in range(m.shape[0]):
                for j in range(m.shape[1]):
                    ax.text(
                        j,
                        i,
                        str(m[i, j]),
                        ha="center",
                        va="center",
                        color="white" if share[i, j] > 0.6 else "black",
                        fontsize=10,
                    )
            ax.set_xticks(range(len(CUES)), CUES)
            ax.set_yticks(range(len(VERDICTS)), VERDICTS)
            acc = res[kind][method]["accuracy_final"]
            ax.set_title(f"{kind.upper()}: {_label(method)}\naccuracy {100 * (acc or 0):.1f} %", fontsize=9)
            ax.set_xlabel("cue at the end of the insertion")
            ax.set_ylabel("true cue")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100, metadata=PNG_METADATA)


def plot_time_to_cue(evaluation: Mapping[str, Any], path: Path) -> None:
    """ECDF of the seconds into the insertion until the cue is right (and stays right)."""
    from matplotlib.figure import Figure

    if (why := _no_results(evaluation)) is not None:
        _placeholder(why, path)
        return
    res = evaluation["results"]
    kinds = [k for k in evaluation["kinds"] if k in res]
    cols = max(len(kinds), 1)
    fig = Figure(figsize=(4.2 * cols, 3.6))
    axes = fig.subplots(1, cols, squeeze=False)[0]
    colors = {"0": "tab:green", "15": "tab:orange", "30": "tab:red", ">=45": "tab:purple"}
    for ax, kind in zip(axes, kinds, strict=False):
        for method, style in (("combined", "-"), ("paper", "--")):
            if method not in res[kind]:
                continue
            for g in DEVIATION_GROUPS:
                d = res[kind][method]["time_to_cue"][g]
                if not d["trials"]:
                    continue
                right = np.asarray(d["seconds"], dtype=float)
                x = np.concatenate([[0.0], right, [12.0]])
                y = np.concatenate([[0.0], np.arange(1, len(right) + 1), [len(right)]]) / d["trials"]
                ax.step(
                    x,
                    y,
                    where="post",
                    color=colors[g],
                    ls=style,
                    lw=1.3,
                    label=f"{g}° {'ours' if method == 'combined' else 'paper'}",
                )
        ax.set_xlim(0, 12)
        ax.set_ylim(0, 1.02)
        ax.set_title(kind.upper(), fontsize=10)
        ax.set_xlabel("seconds into the insertion")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("share of trials with the right cue to the end")
    axes[-1].legend(fontsize=7, loc="lower right", ncol=2)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100, metadata=PNG_METADATA)


def _f(x: float | None, spec: str = ".1f") -> str:
    return "–" if x is None else format(x, spec)


def _rows(res: Mapping[str, Any], kinds: Sequence[str]) -> list[tuple[str, str, str, Mapping[str, Any]]]:
    """(kind, method, label, result) in report order, the reference-force bound last."""
    out = [(k, m, f"{k.upper()}", res[k][m]) for k in kinds for m in METHODS if m in res[k]]
    if REFERENCE in res and "paper" in res[REFERENCE]:
        out.append((REFERENCE, "paper", "measured force (bound)", res[REFERENCE]["paper"]))
    return out


def render_summary(evaluation: Mapping[str, Any], packs: Mapping[float, Mapping[str, Any]]) -> str:
    """The `## Angle cues` section of the report (image links relative to `reports/`). What the stage
    could not build or score is listed, with why, right under the description."""
    not_done = _not_done(evaluation, packs)
    if evaluation.get("skipped") or not packs:
        return _render_built_only(packs, not_done)
    res = evaluation["results"]
    kinds = [k for k in evaluation["kinds"] if k in res]
    ae = evaluation.get("angle_estimate_at_insertion_end")
    some = next(iter(packs.values()))
    pp = some["params"]
    n_trials = sorted(set(evaluation["external_trials"].values()))
    lines = [
        "## Angle cues",
        "",
        "The paper's conclusion as simulator cues: on the preset angle with the force in range, "
        "*continue*; about 15° off, *correct*; 30° or more off, *stop*. **Paper method**: the preset "
        "angle's model predicts the force; a running RMS distance between it and the preset angle's "
        "*standard profile* (mean reference force against time since contact over its training trials, "
        "in units of their spread) is cut by two thresholds, calibrated per model on the training splits "
        "of every angle. **Ours**: the estimator's own volts say at which angle it is held. At rest the "
        "needle's weight loads the tilted tripod differently at each angle; once the tissue pushes back, "
        "the direction in which the three voltages move (log-ratio to rest, taken as the loading reaches "
        "fixed levels) differs too. A linear discriminant per evidence stage, fitted on the training splits "
        "of all angles (temperature by leave-one-batch-out), gives P(angle); the cue is the most probable "
        f"deviation class once its probability reaches {pp['min_confidence']:g}, with the profile's "
        f"force-in-range check (a predicted force above {pp['force_margin']:g}× the preset angle's largest "
        "training force means stop). Both are causal, frame by frame, and debounced "
        f"({pp['debounce_s']:g} s). Scored on the held-out batch: every preset angle against the "
        f"{'/'.join(str(n) for n in n_trials)} held-out trials of every angle; truth from |true − preset|: "
        "0° continue, 15° correct, ≥ 30° stop; the insertion spans the frames labelled `insertion` "
        "(from the reference force, for scoring only: the tracker never sees it).",
        "",
        *([*_NOT_DONE_HEAD, *not_done, ""] if not_done else []),
        "| model | method | right at insertion end | per frame during insertion | "
        "recall continue / correct / stop | force-check stops |",
        "|---|---|---|---|---|---|",
    ]
    for _kind, method, label, r in _rows(res, kinds):
        rec = " / ".join(_f(None if v is None else 100 * v, ".0f") for v in r["recall_final"].values())
        alarms = "–" if r["force_alarm_trials"] is None else f"{r['force_alarm_trials']} trials"
        lines.append(
            f"| {label} | {_label(method)} | {_f(100 * (r['accuracy_final'] or 0))} % | "
            f"{_f(100 * (r['accuracy_frames'] or 0))} % | {rec} % | {alarms} |"
        )
    lines += [
        "",
        "Seconds into the insertion until the cue is right and stays right to its end (median / p90 "
        "over the trials that end right; 0 = right from the first insertion frame, e.g. from the rest "
        "reading), and how many trials end wrong:",
        "",
        "| model | method | " + " | ".join(f"{g}° off" for g in DEVIATION_GROUPS) + " |",
        "|---|---|" + "---|" * len(DEVIATION_GROUPS),
    ]
    for _kind, method, label, r in _rows(res, kinds):
        cells = []
        for g in DEVIATION_GROUPS:
            d = r["time_to_cue"][g]
            cells.append(f"{_f(d['median_s'])} / {_f(d['p90_s'])} s; wrong {d['never_right']}/{d['trials']}")
        lines.append(f"| {label} | {_label(method)} | " + " | ".join(cells) + " |")
    lines += ["", "Confusion at the end of the insertion (rows: true cue; columns: cue shown):", ""]
    header = "| model | method | true cue | " + " | ".join(CUES) + " |"
    lines += [header, "|---|---|---|" + "---|" * len(CUES)]
    for _kind, method, label, r in _rows(res, kinds):
        for name, row in zip(VERDICTS, r["confusion_final"]["counts"], strict=True):
            lines.append(f"| {label} | {_label(method)} | {name} | " + " | ".join(str(v) for v in row) + " |")
    if ae is not None and some.get("angle_estimator"):
        lines += _angle_estimate_lines(ae, some["angle_estimator"])
    lines += [
        "",
        *_findings(res, kinds),
        "",
        "![Confusion matrices of the cues at the end of the insertion](cues/confusion.png)",
        "",
        "![Share of trials with the right cue against seconds into the insertion](cues/time_to_cue.png)",
        "",
    ]
    return "\n".join(lines)


_NOT_DONE_HEAD = ["What this stage could not do, and why:", ""]


def _not_done(evaluation: Mapping[str, Any], packs: Mapping[float, Mapping[str, Any]]) -> list[str]:
    """Bullet lines: what is missing from the packs or the evaluation, and why (empty if nothing)."""
    out = []
    missing = {a: p.get("unavailable") or {} for a, p in sorted(packs.items())}
    reasons = sorted({m["angle_estimator"] for m in missing.values() if "angle_estimator" in m})
    if reasons:
        out.append(
            f"- **No angle estimator** ({'; '.join(reasons)}): the packs have `angle_estimator: null` and "
            "the tracker's cue falls back to the paper's profile method, saying that the angle estimate "
            "is unavailable; only that method is scored."
        )
    whats: dict[tuple[str, str], list[float]] = {}
    for a, m in missing.items():
        for what, why in m.items():
            if what != "angle_estimator":
                whats.setdefault((what, why), []).append(a)
    for (what, why), angles in sorted(whats.items()):
        at = ", ".join(f"{angle_name(a)}°" for a in angles)
        if what == "standard_profile":
            out.append(f"- **No standard profile** at {at} ({why}): no paper-method cue there (it waits).")
        else:
            kind = what.rsplit(".", 1)[-1]
            out.append(f"- **No paper-method thresholds** for {kind} at {at}: {why}.")
    if evaluation.get("skipped"):
        out.append(
            f"- **Cue evaluation skipped**: {evaluation['skipped']}. `cues/evaluation.json` says so; "
            "its two figures only carry that message."
        )
    return out


def _render_built_only(packs: Mapping[float, Mapping[str, Any]], not_done: Sequence[str]) -> str:
    """The section when the cues could not be scored: what was built, what was not, and why."""
    built = []
    if packs:
        some = next(iter(packs.values()))
        per_angle = some["training"]["trials_per_angle"]
        with_profile = [a for a, p in sorted(packs.items()) if p.get("standard_profile")]
        if with_profile:
            built.append(
                f"the standard force profile of {', '.join(f'{angle_name(a)}°' for a in with_profile)}"
            )
        kinds = sorted({k for p in packs.values() for k in p["thresholds"]["profile"]})
        if kinds:
            built.append(f"paper-method thresholds ({', '.join(kinds)})")
        est = some.get("angle_estimator")
        if est:
            built.append(
                f"an angle estimator over {', '.join(f'{a:g}°' for a in est['classes_deg'])} "
                f"({len(est['stages'])} evidence stage(s))"
            )
        text = (
            "Simulator cues (continue / correct / stop from the preset angle's standard force profile and "
            "an angle estimate; see `pipeline/cues.py`). Cue packs were built for the preset angle(s) "
            f"{', '.join(f'{angle_name(a)}°' for a in sorted(packs))} from the training splits (trials per "
            f"angle: {', '.join(f'{a}° {n}' for a, n in per_angle.items())}), with "
            + (", ".join(built) if built else "nothing usable")
            + "."
        )
    else:
        text = "No cue pack was built."
    return "\n".join(["## Angle cues", "", text, "", *_NOT_DONE_HEAD, *not_done, ""])


def _angle_estimate_lines(ae: Mapping[str, Any], estimator: Mapping[str, Any]) -> list[str]:
    stages = estimator["stages"]
    est_cols = ae["cols_estimated_deg"]
    lines = [
        "",
        "Our angle estimate at the end of the insertion (rows: true angle; columns: estimate; the same "
        "for every model and preset angle):",
        "",
        "| true \\ estimated | " + " | ".join(f"{a:g}°" for a in est_cols) + " |",
        "|---|" + "---|" * len(est_cols),
    ]
    for a, row in zip(ae["rows_true_deg"], ae["counts"], strict=True):
        lines.append(f"| {a:g}° | " + " | ".join(str(v) for v in row) + " |")
    lines += [
        "",
        f"Exact in {_f(100 * (ae['exact'] or 0))} % of the held-out trials, within 15° in "
        f"{_f(100 * (ae['within_15'] or 0))} %. Cross-validated accuracy on the training splits "
        f"({estimator['cv']}) per evidence stage: "
        + ", ".join(
            f"{'rest' if i == 0 else f'level {i}'} "
            f"{_f(None if s['cv_accuracy'] is None else 100 * s['cv_accuracy'], '.0f')} %"
            for i, s in enumerate(stages)
        )
        + ".",
    ]
    return lines


def _findings(res: Mapping[str, Any], kinds: Sequence[str]) -> list[str]:
    """What the numbers say, computed, never written in advance."""
    out = []
    for kind in kinds:
        if "combined" not in res[kind]:
            continue
        ours, paper = res[kind]["combined"], res[kind]["paper"]
        a, b = ours["accuracy_final"] or 0, paper["accuracy_final"] or 0
        verdict = "helps" if a > b + 0.02 else ("does not help" if a < b - 0.02 else "changes little")
        line = (
            f"- {kind.upper()}: going past the paper {verdict}: {100 * a:.1f} % against {100 * b:.1f} % "
            "right at the end of the insertion."
        )
        weak = [c for c, v in paper["recall_final"].items() if v is not None and v < 0.5]
        if weak:
            line += f" The profile comparison alone gets under half of the true *{'*, *'.join(weak)}* right."
        weak = [c for c, v in ours["recall_final"].items() if v is not None and v < 0.8]
        if weak:
            line += f" Ours is weak on *{'*, *'.join(weak)}* (recall under 80 %)."
        if ours["force_alarm_trials"]:
            fin = ours["confusion_final"]["counts"]
            line += (
                f" Its force check fired in {ours['force_alarm_trials']} trials "
                f"(true *continue* trials ending on *stop*: {fin[0][3]})."
            )
        out.append(line)
    ref = res.get(REFERENCE, {}).get("paper")
    if ref and kinds:
        best = max((res[k]["paper"]["accuracy_final"] or 0) for k in kinds)
        r = ref["accuracy_final"] or 0
        if r > best + 0.1:
            out.append(
                f"- The profile comparison itself is not the weak link: on the measured force it is right "
                f"in {100 * r:.1f} % of the trials, against at most {100 * best:.1f} % on a model's "
                "prediction. A model trained at one angle maps another angle's volts onto its own angle's "
                "force direction (cutting and friction act along the needle, so they reach the tilted "
                "estimator the same way at every angle), so its predicted profile looks like the preset's "
                "even when the angle is off."
            )
        else:
            out.append(
                f"- On the measured force the profile comparison is right in {100 * r:.1f} % of the trials "
                f"(at most {100 * best:.1f} % on a model's prediction)."
            )
    models_agree = len({json.dumps(res[k].get("combined", {}).get("confusion_final")) for k in kinds}) == 1
    if len(kinds) > 1 and all("combined" in res[k] for k in kinds):
        out.append(
            "- Our cue reads the model's force only for the force-in-range check, so it "
            + (
                "gives the same result with every model."
                if models_agree
                else "differs between models only where that check fired."
            )
        )
    return out


def run(processed_dir: Path, models_dir: Path, out_dir: Path, params: CuesParams, log: Log = _stderr) -> dict:
    """Build the packs from the training splits, evaluate on the external splits, write the outputs."""
    started = time.perf_counter()
    if not Path(models_dir).is_dir():
        raise FileNotFoundError(f"{models_dir}: no such folder (run the train stages first)")
    train = {a: f for a, f in read_split(Path(processed_dir), "train").items() if len(f)}
    if not train:
        raise FileNotFoundError(f"{processed_dir}: no <angle>/train.parquet with rows (run the split stage)")
    cache: dict[Path, Predictor] = {}

    def loader(path: Path) -> Predictor:
        if path not in cache:
            if not (path / "model.pt").is_file():
                raise FileNotFoundError(f"no model checkpoint at {path / 'model.pt'}")
            cache[path] = load_model(path)
        return cache[path]

    packs: dict[float, dict[str, Any]] = {}
    estimator, no_estimator = try_fit_angle_estimator(train, params, log)
    for preset in train:
        preds = {}
        for kind in params.kinds:
            mdir = Path(models_dir) / kind / angle_name(preset)
            if (mdir / "model.pt").is_file():
                preds[kind] = loader(mdir)
            else:
                log(
                    f"warning: no {mdir / 'model.pt'}: no {kind} thresholds in the {angle_name(preset)}° pack"
                )
        t0 = time.perf_counter()
        packs[preset] = build_cue_pack(
            train,
            preset,
            params,
            preds or None,
            log=log,
            angle_estimator=estimator,
            estimator_unavailable=no_estimator,
        )
        log(f"pack for {angle_name(preset)}° built ({time.perf_counter() - t0:.1f} s)")

    available = [
        k
        for k in params.kinds
        if all((Path(models_dir) / k / angle_name(a) / "model.pt").is_file() for a in packs)
    ]
    for k in params.kinds:
        if k not in available:
            log(f"warning: {k} lacks a model for some preset angle, not evaluated")
    if not available:
        evaluation = skipped_evaluation(
            f"no model kind of {list(params.kinds)} has a checkpoint (models/<kind>/<angle>/model.pt) "
            f"for every preset angle ({', '.join(angle_name(a) for a in packs)})",
            packs,
            params,
        )
    else:
        eval_params = params.model_copy(update={"kinds": tuple(available)})
        evaluation = evaluate_cues(processed_dir, models_dir, eval_params, packs, loader=loader, log=log)
    if evaluation.get("skipped"):
        log(f"warning: cue evaluation skipped: {evaluation['skipped']}")

    out_dir = Path(out_dir)
    (out_dir / "packs").mkdir(parents=True, exist_ok=True)
    for stale in (out_dir / "packs").glob("*.json"):  # a pack of an angle no longer trained
        stale.unlink()
    for preset, pack in packs.items():
        (out_dir / "packs" / f"{angle_name(preset)}.json").write_text(
            json.dumps(pack, sort_keys=True, separators=(",", ":"), ensure_ascii=False, allow_nan=False)
            + "\n"
        )
    (out_dir / "evaluation.json").write_text(dump_json(evaluation))
    plot_confusion(evaluation, out_dir / "confusion.png")
    plot_time_to_cue(evaluation, out_dir / "time_to_cue.png")
    (out_dir / "summary.md").write_text(render_summary(evaluation, packs))
    log(f"done in {time.perf_counter() - started:.1f} s -> {out_dir}")
    return evaluation


def main(
    processed_dir: Path,
    models_dir: Path,
    out_dir: Path,
    params: Path = Path("params.yaml"),
) -> None:
    """Build the cue packs (one per preset angle) and evaluate the cues on the external trials."""
    try:
        if not params.is_file():
            raise FileNotFoundError(f"{params}: no such params file")
        run(processed_dir, models_dir, out_dir, load_section(CuesParams, "cues", params))
    except (FileNotFoundError, ValueError) as e:
        _stderr(f"error: {e}")
        raise typer.Exit(1) from e


if __name__ == "__main__":
    typer.run(main)
