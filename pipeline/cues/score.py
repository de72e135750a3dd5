"""Scoring the cues: for every preset angle A and every held-out (external) trial of every true
angle B, a tracker fed the preset model's stored predictions frame by frame, scored against the
truth (|B - A| = 0 -> continue, 15 -> correct, >= 30 -> stop): confusion matrices (at the end of
the insertion and per frame during it), accuracy, and the seconds into the insertion until the cue
is right and stays right to the end. The insertion's start and end come from the `phase` column
(labelled from the reference force), for scoring only; the tracker never sees them.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd

from needlecue_runtime.cues.evidence import UnitMap
from needlecue_runtime.cues.pack import CUES, METHODS, REFERENCE, CuePack, as_pack
from needlecue_runtime.cues.tracker import CueTracker
from needlecue_runtime.cues.units import UnitEvidence, reading_of, unit_evidence
from needlecue_runtime.frontend import Circuit
from needlecue_runtime.vocab import AXES, TRIAL_KEY, angle_name
from pipeline.config import CuesParams
from pipeline.cues.summary import Run, summarise_runs
from pipeline.cues.trials import Trial, trials_of
from pipeline.execution.workers import ordered_map, workers_for
from pipeline.logs import Log

WORTH_A_WORKER = 300_000  # frames replayed: fewer take less than a worker process's start
# (kind, preset angle, true angle) -> the preset model's forces on that angle's external frame
ForcesOf = Callable[[str, float, float], np.ndarray | None]
Packs = Mapping[float, CuePack | Mapping[str, Any]]  # {preset angle: its pack, typed or as built}


@dataclass(frozen=True)
class _Job:
    """One model kind at one preset, tracked on every external trial it has forces for."""

    kind: str
    preset: float
    pack: CuePack
    methods: tuple[str, ...]
    on: list[tuple[float, list[Trial], list[np.ndarray]]]  # (true angle, its trials, forces per trial)
    with_estimator: bool
    count_estimates: bool  # the angle-estimate matrix is counted once: reference force, first preset
    units: Mapping[str, UnitEvidence]  # calibrated units' evidence (training units': in the pack)


def _track(job: _Job) -> tuple[list[Run], list[tuple[float, float]], int, float]:
    """Feed every trial of `job` frame by frame through a fresh tracker: (runs, angle estimates at
    the insertion end, tracker updates, seconds spent in them)."""
    runs: list[Run] = []
    estimates: list[tuple[float, float]] = []
    n_updates, seconds = 0, 0.0
    kinds = job.pack.thresholds.profile
    # one tracker per unit, reset for each of its trials as the live client resets it for each
    # insertion: reading a unit (its class means, the departure test) is done once, not per trial
    trackers: dict[str | None, CueTracker] = {}
    for a, trials, forces in job.on:
        for tr, f in zip(trials, forces, strict=True):
            tracker = trackers.get(tr.unit)
            if tracker is None:
                calibration = job.units.get(tr.unit or "")
                tracker = trackers[tr.unit] = CueTracker(
                    job.pack,
                    job.preset,
                    model_kind=job.kind if job.kind in kinds else None,
                    unit_evidence=unit_evidence(job.pack, tr.unit, calibration),
                    front_end=tr.front_end,
                    reading=reading_of(job.pack, tr.unit, calibration),
                    unit_map=tr.unit_map,
                )
            else:
                tracker.use_front_end(tr.front_end)
                tracker.use_unit_map(tr.unit_map)
                tracker.reset()
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
            seconds += time.perf_counter() - t0
            n_updates += n
            est = tracker.angle_map_deg
            for m in job.methods:
                if m == "combined" and not job.with_estimator:
                    continue
                combined = m == "combined"
                runs.append(
                    Run(
                        job.kind,
                        m,
                        job.preset,
                        a,
                        tr.t,
                        codes[m],
                        tr.ins_start,
                        tr.ins_end,
                        est if combined else None,
                        alarm and combined,
                        tr.unit,
                    )
                )
            if job.count_estimates and job.with_estimator:
                estimates.append((a, est if est is not None else math.nan))
    return runs, estimates, n_updates, seconds


@dataclass(frozen=True)
class Tracked:
    """The tracker runs of a cue evaluation, before they are summarised (`cue_document`). A group of
    its trials (the trials of some units) is summarised from them without replaying it: a run
    depends on its trial alone (each unit's tracker is reset for each trial)."""

    runs: tuple[Run, ...]
    trials: Mapping[float, Sequence[Trial]]  # {true angle: its scored trials}
    angle_conf: Mapping[tuple[float, float], int]  # {(true, estimated angle): trials}
    with_estimator: bool
    skipped: str | None = None  # why nothing was scored (then nothing else is set)


def evaluate_cues(
    external: Mapping[float, pd.DataFrame],
    params: CuesParams,
    packs: Packs,
    forces_of: ForcesOf,
    *,
    log: Log,
    units: Mapping[str, UnitEvidence] | None = None,
    circuits: Mapping[str, Circuit | None] | None = None,
    paper_bound: bool = True,
    maps: Mapping[str, UnitMap] | None = None,
) -> dict[str, Any]:
    """Cue quality on the external trials of every angle (`track_external`, then `cue_document`)."""
    tracked = track_external(
        external,
        params,
        packs,
        forces_of,
        log=log,
        units=units,
        circuits=circuits,
        paper_bound=paper_bound,
        maps=maps,
    )
    return cue_document(tracked, params, packs)


def track_external(
    external: Mapping[float, pd.DataFrame],
    params: CuesParams,
    packs: Packs,
    forces_of: ForcesOf,
    *,
    log: Log,
    units: Mapping[str, UnitEvidence] | None = None,
    circuits: Mapping[str, Circuit | None] | None = None,
    paper_bound: bool = True,
    maps: Mapping[str, UnitMap] | None = None,
) -> Tracked:
    """The trackers' runs on the external trials of every angle, for every preset angle with a pack;
    each trial read through its unit's declared circuit in `circuits` (else the pack's).

    `external`: {true angle: its external frame}; `forces_of(kind, preset, true angle)`: the preset
    angle's `kind` model's forces on that frame, rows in frame order (None: no such model). `units`:
    the calibrated units' evidence (`pipeline.cues.unit_evidence`); a trial of a unit neither there nor
    among the pack's training units is read as the average unit's. `maps`: the calibrated units read
    through their map (`needlecue_runtime.cues.units.cue_reading`), {unit_id: map}. `paper_bound`: also
    score the paper's method on the measured force (its upper bound; the angle-estimate matrix comes with it).
    Without external trials with an insertion phase there is nothing to score: `skipped` says why.
    The combined method is scored only with an angle estimator."""
    external = {float(a): f for a, f in external.items() if len(f)}
    units = dict(units or {})
    if not external:
        return _skipped("no external trials (no <angle>/external.parquet with rows)")
    if not packs:
        return _skipped("no cue pack")
    packs = _typed(packs)  # checked once: every job's trackers read them
    channels = list(next(iter(packs.values())).channels)
    trials: dict[float, list[Trial]] = {}
    for a, f in external.items():
        missing = [c for c in channels if c not in f.columns]
        if missing:
            raise ValueError(f"the {angle_name(a)}° external set lacks channel(s) {missing}")
        keep = [tr for tr in trials_of(f, channels, a, circuits, maps) if tr.ins_start >= 0]
        if len(keep) < f.groupby(list(TRIAL_KEY)).ngroups:
            log(f"warning: {angle_name(a)}°: trials without an insertion phase skipped")
        trials[a] = keep
    if not any(trials.values()):
        return _skipped("no external trial has frames labelled 'insertion' (nothing to score)")
    with_estimator = all(p.angle_estimator is not None for p in packs.values())
    # The tracker is pure Python, one frame at a time: scoring ~1M frames is this stage's work,
    # so the (kind, preset) jobs run on every core.
    jobs: list[_Job] = []
    for preset, pack in sorted(packs.items()):
        if not paper_bound:  # the paper's method on the measured force is not asked for
            break
        # the paper's comparison on the measured force: not deployable, its upper bound
        axes = pack.standard_profile.axes if pack.standard_profile is not None else AXES
        measured = {a: [tr.force_on(axes) for tr in trials[a]] for a in external}
        # an angle whose reference records other axes than the preset's has no measured profile
        on = [(a, trials[a], f) for a, f in measured.items() if all(x is not None for x in f)]
        jobs.append(
            _Job(REFERENCE, preset, pack, ("paper",), on, with_estimator, preset == min(packs), units)
        )
    for kind in params.kinds:
        for preset, pack in sorted(packs.items()):
            on = []
            for a in external:
                forces = forces_of(kind, preset, a)
                if forces is None:
                    where = f"the {angle_name(preset)}° model on {angle_name(a)}°"
                    log(f"warning: no {kind} predictions of {where}")
                    continue
                on.append((a, trials[a], [forces[tr.rows] for tr in trials[a]]))
            jobs.append(_Job(kind, preset, pack, METHODS, on, with_estimator, False, units))
    runs: list[Run] = []
    angle_conf: dict[tuple[float, float], int] = {}
    n_updates, seconds = 0, 0.0
    frames = sum(len(rows) for job in jobs for _, _, forces in job.on for rows in forces)
    workers = workers_for(frames, WORTH_A_WORKER)
    for job, (job_runs, estimates, n, busy) in zip(jobs, ordered_map(_track, jobs, workers), strict=True):
        runs += job_runs
        for key in estimates:
            angle_conf[key] = angle_conf.get(key, 0) + 1
        n_updates, seconds = n_updates + n, seconds + busy
        if job.kind != REFERENCE:
            trials_seen = sum(len(tr) for _, tr, _ in job.on)
            log(f"{job.kind} at {angle_name(job.preset)}°: {trials_seen} trials ({busy:.1f} s)")
    if n_updates:
        log(
            f"{n_updates} tracker updates, {1e6 * seconds / n_updates:.1f} µs each on average "
            f"(including the evaluation loop; {workers} worker process(es))"
        )
    return Tracked(tuple(runs), trials, angle_conf, with_estimator)


def _skipped(reason: str) -> Tracked:
    return Tracked((), {}, {}, False, reason)


def cue_document(tracked: Tracked, params: CuesParams, packs: Packs) -> dict[str, Any]:
    """The cue evaluation of tracker runs: confusion matrices, accuracy, time to cue and what a
    trainee sees, per kind and method (or `skipped_evaluation`, saying why nothing was scored)."""
    if tracked.skipped is not None:
        return skipped_evaluation(tracked.skipped, packs, params)
    trials = tracked.trials
    summary = summarise_runs(
        tracked.runs, params.continue_below_deg, params.stop_from_deg, params.cue_within_s
    )
    classes = sorted(trials)
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
        "angle_estimate_at_insertion_end": _angle_matrix(classes, packs, tracked.angle_conf)
        if tracked.with_estimator
        else None,
        "results": summary,
    }
    unavailable = _unavailable(packs)
    if unavailable:
        out["unavailable"] = unavailable
    return out


def _angle_matrix(classes: Sequence[float], packs: Packs, angle_conf: Mapping[tuple, int]) -> dict[str, Any]:
    est = [p.angle_estimator for p in _typed(packs).values()]
    est_classes = sorted({c for e in est if e is not None for c in e.classes_deg})
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


def _unavailable(packs: Packs) -> dict[str, dict[str, str]]:
    """{preset angle: {what: why}} over the packs that lack something."""
    return {angle_name(a): dict(p.unavailable) for a, p in sorted(_typed(packs).items()) if p.unavailable}


def _typed(packs: Packs) -> dict[float, CuePack]:
    return {a: as_pack(p) for a, p in packs.items()}


def skipped_evaluation(reason: str, packs: Packs, params: CuesParams) -> dict[str, Any]:
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
