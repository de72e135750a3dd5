"""Scoring the cues of refitted angle estimators: each job fits the estimator and the cue packs on some
training trials, then scores the combined cue on test trials with `evaluate_cues` (the measured force
standing in for the model: the combined cue reads the force only for its force-in-range check), a
unit's calibration insertions read as its evidence where given. A tracker fed frame by frame is the
slow part: the jobs run on the machine's cores (`pipeline.execution.workers`), the same figures on
any number."""

from __future__ import annotations

import os
import time
from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd

from needlecue_runtime.frontend import Circuit
from needlecue_runtime.vocab import axes_of, channels_of
from pipeline.config import CuesParams
from pipeline.cues.estimator import try_fit_angle_estimator
from pipeline.cues.packs import build_cue_pack
from pipeline.cues.score import WORTH_A_WORKER, evaluate_cues
from pipeline.cues.unit_evidence import evidence_of, trial_features
from pipeline.execution.workers import WORKERS_ENV, ordered_imap, workers_for
from pipeline.logs import Log
from pipeline.needs.subsample import Key, Selection, select

SEEN = ("wrong_final", "wrong_frames", "coverage_frames")  # what the trainee sees, of `seen`
Frames = Mapping[str, Mapping[float, pd.DataFrame]]  # {split: {angle: rows}}


@dataclass(frozen=True)
class CueScoring:
    """One scoring of the combined cue on the `test` trials ({split: selection}); `evidence`, the
    trials ({split: selection}) that are `unit`'s calibration (None: the pack's evidence of each unit)."""

    tag: tuple[Any, ...]
    test: Mapping[str, Selection]
    unit: str | None = None
    evidence: Mapping[str, Selection] | None = None


@dataclass(frozen=True)
class CueJob:
    """The angle estimator and packs fitted on `fit_on` (training trials), then each scoring."""

    fit_on: Selection
    scorings: tuple[CueScoring, ...]


_DATA: dict[str, Any] = {}  # a worker's copy of the frames, circuits and params


def _set_data(
    frames: Frames,
    circuits: Mapping[str, Circuit | None],
    params: CuesParams,
    in_pool: bool,
) -> None:
    _DATA.update(frames=frames, circuits=circuits, params=params)
    if in_pool:  # a worker process: evaluate_cues must not start processes of its own
        os.environ[WORKERS_ENV] = "1"


def _pick(frames: Frames, by_split: Mapping[str, Selection]) -> dict[float, pd.DataFrame]:
    """{angle: the selected trials' rows over the splits}, angles with none left out."""
    parts: dict[float, list[pd.DataFrame]] = {}
    for split, sel in sorted(by_split.items()):
        for a, keys in sel.items():
            if keys:
                parts.setdefault(a, []).append(select(frames[split][a], keys))
    return {a: pd.concat(p, ignore_index=True) for a, p in sorted(parts.items())}


def cue_figures(evaluation: Mapping[str, Any]) -> dict[str, Any]:
    """The combined cue's figures of an `evaluate_cues` result (its one kind, on the measured force)."""
    kind = next(iter(evaluation.get("kinds") or []), None)
    combined = ((evaluation.get("results") or {}).get(kind) or {}).get("combined")
    if not combined:
        return {"unavailable": evaluation.get("skipped") or "the combined cue was not scored"}
    return {
        "balanced_within_s": combined["balanced_within_s"],
        "recall_within_s": combined["recall_within_s"],
        "seen": {k: combined["seen"][k] for k in SEEN},
        "trials": sum((evaluation.get("external_trials") or {}).values()),
    }


def _score_job(job: CueJob) -> tuple[list[dict[str, Any]], float]:
    """(each scoring's `cue_figures`, seconds) of one job, on the data `_set_data` gave."""
    started = time.perf_counter()
    frames, circuits, params = _DATA["frames"], _DATA["circuits"], _DATA["params"]
    train = _pick(frames, {"train": job.fit_on})
    estimator, why = try_fit_angle_estimator(train, params, None, circuits)
    if estimator is None:
        why = f"no angle estimator could be fitted ({why})"
        return [{"unavailable": why} for _ in job.scorings], time.perf_counter() - started
    packs = {
        a: build_cue_pack(train, a, params, None, angle_estimator=estimator, circuits=circuits) for a in train
    }
    channels = channels_of(next(iter(train.values())))
    # the combined cue reads a model only for its force check, and here every "model" is the measured
    # force: one kind gives every kind's figures (and the paper's method is not asked for)
    one_kind = params.model_copy(update={"kinds": params.kinds[:1]})
    out = []
    for scoring in job.scorings:
        test = _pick(frames, scoring.test)
        units = {}
        if scoring.unit is not None and scoring.evidence is not None:
            calib = _pick(frames, scoring.evidence)
            trials = trial_features(calib, channels, params, circuits, estimator["levels"])[0]
            units = {scoring.unit: evidence_of(trials, len(channels)).get(scoring.unit, {})}
        evaluation = evaluate_cues(
            test,
            one_kind,
            packs,
            lambda _kind, _preset, a, test=test: test[a][list(axes_of(test[a].columns))].to_numpy(np.float64),
            log=lambda _m: None,
            units=units,
            circuits=circuits,
            paper_bound=False,
        )
        out.append(cue_figures(evaluation))
    return out, time.perf_counter() - started


def _sizes(frames: Frames) -> dict[tuple[str, float], dict[Key, int]]:
    """{(split, angle): {trial: its rows}}."""
    out = {}
    for split, by_angle in frames.items():
        for a, f in by_angle.items():
            pairs = zip(f["batch_id"].astype(str), f["trial_id"].astype(str), strict=True)
            out[split, a] = dict(Counter(pairs))
    return out


def score_cues(
    jobs: Sequence[CueJob],
    frames: Frames,
    circuits: Mapping[str, Circuit | None],
    params: CuesParams,
    log: Log,
) -> dict[tuple[Any, ...], dict[str, Any]]:
    """{scoring tag: its `cue_figures`} of every job, the jobs on the machine's cores when they repay
    a worker's start (the same figures either way)."""
    # frames replayed: each test trial once per preset, by the reference job and the "ls" job
    sizes = _sizes(frames)
    work = [
        sum(
            2 * len(j.fit_on) * sizes[split, a][k]
            for s in j.scorings
            for split, sel in s.test.items()
            for a, keys in sel.items()
            for k in keys
        )
        for j in jobs
    ]
    order = sorted(range(len(jobs)), key=lambda i: (-work[i], i))  # the longest first: no long tail
    workers = workers_for(sum(work), WORTH_A_WORKER)
    in_pool = workers > 1 and len(jobs) > 1
    args = (frames, circuits, params, in_pool)
    found: dict[tuple[Any, ...], dict[str, Any]] = {}
    try:
        results = ordered_imap(_score_job, [jobs[i] for i in order], workers, _set_data, args)
        for i, (figures, seconds) in zip(order, results, strict=True):
            job = jobs[i]
            found.update({s.tag: f for s, f in zip(job.scorings, figures, strict=True)})
            fitted = sum(len(k) for k in job.fit_on.values())
            log(f"cues fitted on {fitted} training trials, {len(job.scorings)} scoring(s) ({seconds:.1f} s)")
    finally:
        _DATA.clear()  # the in-process run's copy of the data
    return found
