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

from pipeline.config import CuesParams
from pipeline.cues.tracker import (
    CUES,
    METHODS,
    REFERENCE,
    VERDICTS,
    CueTracker,
    UnitEvidence,
    UnitMap,
    cue_for_deviation,
    reading_of,
    unit_evidence,
)
from pipeline.cues.trials import Trial, trials_of
from pipeline.execution.workers import ordered_map, workers_for
from pipeline.frontend import Circuit
from pipeline.logs import Log
from pipeline.vocab import AXES, TRIAL_KEY, angle_name

DEVIATION_GROUPS = ("0", "15", "30", ">=45")
WORTH_A_WORKER = 300_000  # frames replayed: fewer take less than a worker process's start
# (kind, preset angle, true angle) -> the preset model's forces on that angle's external frame
ForcesOf = Callable[[str, float, float], np.ndarray | None]


def deviation_group(dev_deg: float) -> str:
    d = round(abs(dev_deg), 6)
    return "0" if d == 0 else "15" if d == 15 else "30" if d == 30 else ">=45"


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
    unit: str | None = None  # the estimator unit that recorded the trial


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


def _shown(codes: np.ndarray) -> np.ndarray:
    """Which cue codes are an angle cue shown to the trainee (continue, correct or stop)."""
    return (codes >= 1) & (codes <= len(VERDICTS))


def trainee_view(final: np.ndarray, frames: np.ndarray, wrong_ever: int) -> dict[str, float | None]:
    """What a trainee sees, from the confusion matrices (rows: true continue / correct / stop; columns:
    CUES) at the insertion's end and over its frames, and the insertions that showed a wrong cue at
    some frame: the share of insertions ending on a wrong cue, of insertions showing one at any time,
    of insertion frames showing one, and of insertion frames showing a cue at all (coverage)."""
    n, nf = int(final.sum()), int(frames.sum())
    cue_cols = slice(1, 1 + len(VERDICTS))

    def wrong(m: np.ndarray) -> int:
        return int(m[:, cue_cols].sum() - np.trace(m[:, cue_cols]))

    return {
        "wrong_final": wrong(final) / n if n else None,
        "wrong_ever": wrong_ever / n if n else None,
        "wrong_frames": wrong(frames) / nf if nf else None,
        "coverage_frames": int(frames[:, cue_cols].sum()) / nf if nf else None,
    }


def summarise_runs(
    runs: Sequence[Run], continue_below: float = 7.5, stop_from: float = 22.5, within_s: float = 3.0
) -> dict[str, Any]:
    """Confusion matrices, accuracy and time to cue of tracker runs, per (kind, method); and per true
    cue, the share of trials whose cue was right, and stayed right, within `within_s` of the insertion's
    start (their mean over the cues present: `balanced_within_s`)."""
    out: dict[str, Any] = {}
    for run in runs:
        true = VERDICTS.index(cue_for_deviation(run.true_angle - run.preset, continue_below, stop_from)) + 1
        d = out.setdefault(run.kind, {}).setdefault(
            run.method,
            {
                "final": np.zeros((3, len(CUES)), dtype=np.int64),
                "frames": np.zeros((3, len(CUES)), dtype=np.int64),
                "wrong_ever": 0,
                "ttc": {g: [] for g in DEVIATION_GROUPS},
                "n": {g: 0 for g in DEVIATION_GROUPS},
                "right_final": {g: 0 for g in DEVIATION_GROUPS},
                "alarms": 0,
                "in_time": np.zeros((3, 2), dtype=np.int64),  # per true cue: [trials, right within_s]
            },
        )
        seg = run.codes[run.ins_start : run.ins_end + 1]
        d["final"][true - 1, run.codes[run.ins_end]] += 1
        d["frames"][true - 1] += np.bincount(seg, minlength=len(CUES))
        d["wrong_ever"] += int(bool(np.any(_shown(seg) & (seg != true))))
        g = deviation_group(run.true_angle - run.preset)
        d["n"][g] += 1
        d["right_final"][g] += int(run.codes[run.ins_end] == true)
        d["alarms"] += int(run.alarm)
        ttc = time_to_cue(run.t, run.codes == true, run.ins_start, run.ins_end)
        d["ttc"][g].append(ttc)
        d["in_time"][true - 1] += (1, int(ttc is not None and ttc <= within_s + 1e-9))
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
            in_time = d["in_time"]
            recall_in_time = {
                c: (float(in_time[i, 1] / in_time[i, 0]) if in_time[i, 0] else None)
                for i, c in enumerate(VERDICTS)
            }
            known = [v for v in recall_in_time.values() if v is not None]
            result.setdefault(kind, {})[method] = {
                "within_s": within_s,
                "recall_within_s": recall_in_time,
                "balanced_within_s": float(np.mean(known)) if known else None,
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
                "seen": trainee_view(fin, frm, d["wrong_ever"]),
                "time_to_cue": ttc,
                "force_alarm_trials": d["alarms"] if method == "combined" else None,
            }
    return result


@dataclass(frozen=True)
class _Job:
    """One model kind at one preset, tracked on every external trial it has forces for."""

    kind: str
    preset: float
    pack: Mapping[str, Any]
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
    kinds = job.pack["thresholds"]["profile"]
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
    packs: Mapping[float, Mapping[str, Any]],
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
    packs: Mapping[float, Mapping[str, Any]],
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
    through their map (`pipeline.cues.tracker.cue_reading`), {unit_id: map}. `paper_bound`: also score the
    paper's method on the measured force (its upper bound; the angle-estimate matrix comes with it).
    Without external trials with an insertion phase there is nothing to score: `skipped` says why.
    The combined method is scored only with an angle estimator."""
    external = {float(a): f for a, f in external.items() if len(f)}
    units = dict(units or {})
    if not external:
        return _skipped("no external trials (no <angle>/external.parquet with rows)")
    if not packs:
        return _skipped("no cue pack")
    first = next(iter(packs.values()))
    channels = list(first["channels"])
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
    with_estimator = all(p.get("angle_estimator") for p in packs.values())
    # The tracker is pure Python, one frame at a time: scoring ~1M frames is this stage's work,
    # so the (kind, preset) jobs run on every core.
    jobs: list[_Job] = []
    for preset, pack in sorted(packs.items()):
        if not paper_bound:  # the paper's method on the measured force is not asked for
            break
        # the paper's comparison on the measured force: not deployable, its upper bound
        axes = (pack.get("standard_profile") or {}).get("axes") or AXES
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


def cue_document(
    tracked: Tracked, params: CuesParams, packs: Mapping[float, Mapping[str, Any]]
) -> dict[str, Any]:
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


UNIT_GROUPS = ("same_unit", "new_uncalibrated", "new_calibrated")
GROUP_KEYS = ("balanced_within_s", "recall_within_s", "within_s", "accuracy_final", "confusion_final", "seen")
# (kind, preset angle, true angle, split) -> the preset model's forces on that angle's `split` frame
ForcesOfSplit = Callable[[str, float, float, str], np.ndarray | None]


def _group_mask(
    frame: pd.DataFrame, group: str, roles: Mapping[str, str], calibrated: Mapping[str, bool]
) -> np.ndarray:
    if "unit_id" not in frame.columns:
        return np.zeros(len(frame), dtype=bool)
    units = frame["unit_id"].astype(str)
    if group == "same_unit":
        return units.map(lambda u: roles.get(u) == "training").to_numpy(bool)
    return units.map(lambda u: roles.get(u, "new") != "training" and bool(calibrated.get(u))).to_numpy(bool)


def evaluate_unit_groups(
    external: Mapping[float, pd.DataFrame],
    units: Mapping[str, UnitEvidence],
    params: CuesParams,
    packs: Mapping[float, Mapping[str, Any]],
    forces_of: ForcesOfSplit,
    uncalibrated_split: str,
    roles: Mapping[str, str],
    calibrated: Mapping[str, bool],
    circuits: Mapping[str, Circuit | None] | None = None,
    tracked: Tracked | None = None,
    maps: Mapping[str, UnitMap] | None = None,
) -> dict[str, Any]:
    """The cues scored per unit group: the training units' external trials (`same_unit`), and the
    external trials of new units that have a calibration, without it (`new_uncalibrated`: the angle
    estimator reads them as the average unit's, forces from `uncalibrated_split`) and with it
    (`new_calibrated`: `units` holds their calibrations' evidence, `maps` the maps some are read
    through). Per group, kind and method:
    balanced accuracy within `cue_within_s`, per-cue recall, final confusion matrix.

    `tracked`: the runs of `evaluate_cues` on all of `external` (the external forces, `units`,
    `circuits`), whose trials of the same-unit and calibrated groups are then summarised, not
    replayed: the same figures, for a third of the tracker's work."""
    out: dict[str, Any] = {}
    source = {float(a): f for a, f in external.items()}
    if (
        tracked is not None
        and tracked.skipped is None
        and set(tracked.trials) != {a for a, f in source.items() if len(f)}
    ):
        raise ValueError(
            f"the tracked runs are of angles {sorted(tracked.trials)}, not of these external trials"
        )
    for group in UNIT_GROUPS:
        masks = {a: _group_mask(f, group, roles, calibrated) for a, f in source.items()}
        frames = {a: source[a][m].reset_index(drop=True) for a, m in masks.items() if m.any()}
        if not frames:
            continue
        members = sorted({str(u) for f in frames.values() for u in f["unit_id"].unique()})
        if tracked is not None and tracked.skipped is None and group != "new_uncalibrated":
            out[group] = _group_of(tracked, set(members), sorted(frames), params)
            continue
        split = uncalibrated_split if group == "new_uncalibrated" else "external"

        def forces(
            kind: str, preset: float, a: float, split: str = split, masks: dict = masks
        ) -> np.ndarray | None:
            full = forces_of(kind, preset, a, split)
            if full is None and split != "external":  # that model had no calibration for these units
                full = forces_of(kind, preset, a, "external")
            return None if full is None else full[masks[a]]

        calibrated_now = group != "new_uncalibrated"  # an uncalibrated unit has neither evidence nor map
        ev = evaluate_cues(
            frames,
            params,
            packs,
            forces,
            log=lambda _m: None,
            units=units if calibrated_now else {},
            circuits=circuits,
            maps=maps if calibrated_now else None,
        )
        out[group] = {
            "units": members,
            "external_trials": ev.get("external_trials"),
            "results": _group_results(ev.get("results") or {}),
        }
    return out


def _group_of(
    tracked: Tracked, members: set[str], angles: Sequence[float], params: CuesParams
) -> dict[str, Any]:
    """A unit group's figures from the runs of its `members`' trials at `angles`, as `evaluate_cues`
    on those trials alone gives them."""
    trials = {a: [tr for tr in tracked.trials.get(a, ()) if tr.unit in members] for a in angles}
    if not any(trials.values()):  # nothing with an insertion to score: a skipped evaluation's fields
        return {"units": sorted(members), "external_trials": None, "results": {}}
    runs = [r for r in tracked.runs if r.unit in members and r.true_angle in trials]
    summary = summarise_runs(runs, params.continue_below_deg, params.stop_from_deg, params.cue_within_s)
    return {
        "units": sorted(members),
        "external_trials": {angle_name(a): len(trials[a]) for a in angles},
        "results": _group_results(summary),
    }


def _group_results(results: Mapping[str, Mapping[str, Mapping[str, Any]]]) -> dict[str, Any]:
    return {
        kind: {m: {k: r.get(k) for k in GROUP_KEYS} for m, r in methods.items()}
        for kind, methods in results.items()
    }
