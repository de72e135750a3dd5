"""The curves of "how much data you need", from the lab's own processed data.

Training insertions per angle: a ladder of counts (`pipeline.needs.subsample.ladder`); at each, a
subsample of every angle's training trials spread over the units and their batches (a count's
subsample holds those of the smaller counts, so that two steps differ by the data added, not by another
draw). On each: the force of each model kind (LS itself, the networks' stand-in) refitted per angle
(`pipeline.needs.force`), and the cues of the angle estimator and packs refitted (`pipeline.needs.scoring`),
both scored on the training units' external trials.

Calibration insertions per angle, cues only (force would need the models retrained without the unit):
each new unit's first k calibration insertions per angle (by batch and trial id) as its evidence,
scored on its external trials by the estimator of every training trial; and, with two training units
or more, each left out in turn: the estimator fitted on the others, k of its own training insertions
per angle as its calibration, scored on its external trials and its training trials beyond the
largest k (the same trials for every k).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from needlecue_runtime.frontend import Circuit
from needlecue_runtime.vocab import angle_name
from pipeline.calibration.rows import calibration_rows
from pipeline.config import CuesParams, NeedsParams
from pipeline.dataset.splits import SplitFiles, unit_roles
from pipeline.logs import Log
from pipeline.metrics.scores import mean_known
from pipeline.needs.document import FORMAT
from pipeline.needs.force import ForceModel, force_curve
from pipeline.needs.scoring import SEEN, CueJob, CueScoring, Frames, score_cues
from pipeline.needs.subsample import SUBSAMPLE, Key, Selection, ladder, spread_order, trials_in, units_of


def note(what: str, why: str) -> dict[str, str]:
    """One entry of `not_computed`."""
    return {"what": what, "why": why}


@dataclass(frozen=True)
class LabData:
    """What the curves read: per split ("train", "external", "calibration") {angle: rows}, each unit's
    declared circuit, and the new units (the manifest's role "new")."""

    frames: Frames
    circuits: Mapping[str, Circuit | None]
    new_units: Sequence[str]

    @property
    def training_units(self) -> list[str]:
        """The units with training trials."""
        return sorted({u for f in self.frames.get("train", {}).values() for u in units_of(f).unique()})


def lab_data(data_dir: Path) -> LabData:
    """The split stage's output as the curves read it (FileNotFoundError without training trials)."""
    files = SplitFiles(data_dir)
    train = {a: f for a, f in files.by_angle("train").items() if len(f)}
    if not train:
        raise FileNotFoundError(f"{data_dir}: no <angle>/train.parquet with rows (run the split stage)")
    rows = list(calibration_rows(data_dir).values())
    every = pd.concat(rows, ignore_index=True) if rows else pd.DataFrame()
    calibration = {float(a): f.reset_index(drop=True) for a, f in every.groupby("angle_deg")} if rows else {}
    frames = {"train": train, "external": files.by_angle("external"), "calibration": calibration}
    roles = unit_roles(data_dir)  # a unit the manifest does not know, with a calibration batch, is new
    found = {u for f in calibration.values() for u in units_of(f).unique()}
    new = [u for u in sorted(found) if roles.get(u, "new") == "new"]
    data = LabData(frames, files.front_ends(), new)
    return LabData(frames, data.circuits, [u for u in new if u not in data.training_units])


class _Plan:
    """Cue scorings grouped by the training trials their estimator is fitted on (one fit each)."""

    def __init__(self) -> None:
        self.fits: dict[tuple[Any, ...], tuple[Selection, list[CueScoring]]] = {}

    def add(self, fit_on: Selection, scoring: CueScoring) -> None:
        key = tuple((a, tuple(sorted(k))) for a, k in sorted(fit_on.items()))
        self.fits.setdefault(key, (fit_on, []))[1].append(scoring)

    def jobs(self) -> list[CueJob]:
        return [CueJob(sel, tuple(s)) for sel, s in self.fits.values()]


def _unit_keys(frames: Mapping[float, pd.DataFrame], unit: str) -> Selection:
    """{angle: the unit's trials, sorted by (batch_id, trial_id)}, angles without any left out."""
    out = {a: sorted(k for u, k in trials_in(f) if u == unit) for a, f in frames.items()}
    return {a: k for a, k in out.items() if k}


def _calibration_plan(
    frames: Frames,
    new_units: Sequence[str],
    p: NeedsParams,
    orders: Mapping[float, list[Key]],
    owner: Mapping[Key, str],
    plan: _Plan,
) -> tuple[dict[str, Any], list[dict[str, str]]]:
    """The calibration scorings (added to `plan`) and their layout: {"new_units": {unit: {...}},
    "leave_one_unit_out": {unit: {...}}, or None with fewer than two training units}."""
    external, calibration = frames.get("external", {}), frames.get("calibration", {})
    units = sorted(set(owner.values()))
    notes: list[dict[str, str]] = []
    every = {a: list(o) for a, o in orders.items()}
    new: dict[str, Any] = {}
    for unit in new_units:
        mine, test = _unit_keys(calibration, unit), _unit_keys(external, unit)
        if not mine or not test:
            why = "no calibration batch" if not mine else "no external trial to score on"
            notes.append(note(f"{unit}'s cues against calibration insertions", why))
            continue
        fewest = min(map(len, mine.values()))
        new[unit] = {"calibration_insertions": {angle_name(a): len(k) for a, k in mine.items()}, "k": []}
        for k in p.calibration_insertions:
            if k > fewest:
                why = f"its calibration batch has {fewest} insertion(s) at some angle"
                notes.append(note(f"{unit} with {k} calibration insertions per angle", why))
                continue
            new[unit]["k"].append(k)
            evidence = {"calibration": {a: keys[:k] for a, keys in mine.items()}}
            plan.add(every, CueScoring(("new", unit, k), {"external": test}, unit, evidence))
    if len(units) < 2:
        why = f"one training unit ({units[0]}): no other unit to fit the estimator on"
        notes.append(note("leave-one-unit-out calibration curve", why))
        return {"new_units": new, "leave_one_unit_out": None}, notes
    left: dict[str, Any] = {}
    for unit in units:
        mine = {a: [k for k in o if owner[k] == unit] for a, o in orders.items()}  # spread over batches
        others = {a: kept for a, o in orders.items() if (kept := [k for k in o if owner[k] != unit])}
        fewest = min(map(len, mine.values()))
        ks = [k for k in p.calibration_insertions if k <= fewest]
        for k in p.calibration_insertions[len(ks) :]:
            why = f"it has {fewest} training insertion(s) at some angle"
            notes.append(note(f"{unit} left out with {k} calibration insertions per angle", why))
        if not ks:
            continue
        # the same test trials for every k: its external trials and its training trials past the largest k
        test = {"train": {a: m[max(ks) :] for a, m in mine.items()}, "external": _unit_keys(external, unit)}
        scored = sum(len(k) for sel in test.values() for k in sel.values())
        if not scored:
            notes.append(note(f"{unit} left out", "no trial of it is left to score on"))
            continue
        left[unit] = {"test_trials": scored, "k": ks}
        for k in ks:
            evidence = {"train": {a: m[:k] for a, m in mine.items()}}
            plan.add(others, CueScoring(("loo", unit, k), test, unit, evidence))
    return {"new_units": new, "leave_one_unit_out": left}, notes


def _mean_figures(figures: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """The mean balanced accuracy and `seen` of figures that have them, and how many did."""
    known = [f for f in figures if f.get("balanced_within_s") is not None]
    if not known:
        return {"units": 0}
    return {
        "units": len(known),
        "balanced_within_s": float(np.mean([f["balanced_within_s"] for f in known])),
        "seen": {k: mean_known(f["seen"].get(k) for f in known) for k in SEEN},
    }


def _calibration_figures(
    layout: Mapping[str, Any], found: Mapping[tuple[Any, ...], dict[str, Any]]
) -> tuple[dict[str, Any], dict[str, Any] | None]:
    """(new units, leave-one-unit-out) of the calibration `layout` with their scored figures: per unit
    its steps, and for the units left out the mean over them at each k."""
    new = {
        unit: {
            **{k: v for k, v in entry.items() if k != "k"},
            "steps": [{"k": k, **found["new", unit, k]} for k in entry["k"]],
        }
        for unit, entry in layout["new_units"].items()
    }
    if layout["leave_one_unit_out"] is None:
        return new, None
    units = {
        unit: {
            "test_trials": entry["test_trials"],
            "steps": [{"k": k, **found["loo", unit, k]} for k in entry["k"]],
        }
        for unit, entry in layout["leave_one_unit_out"].items()
    }
    ks = sorted({s["k"] for e in units.values() for s in e["steps"]})
    mean = [
        {"k": k, **_mean_figures([s for e in units.values() for s in e["steps"] if s["k"] == k])} for k in ks
    ]
    return new, {"units": units, "mean": mean}


def needs_curves(
    data: LabData,
    p: NeedsParams,
    cues: CuesParams,
    models: Mapping[str, ForceModel],
    cue_kind: str,
    log: Log,
) -> dict[str, Any]:
    """The needs document (without its advice, `pipeline.needs.document.Curves`): the ladder with force
    and cue figures per step, the calibration curves, and what was not computed and why. The cues are
    scored as for `cue_kind`'s pack, the measured force standing in for its model. ValueError without
    training trials."""
    train = {a: f for a, f in sorted(data.frames.get("train", {}).items()) if len(f)}
    if not train:
        raise ValueError("no training trials (no <angle>/train.parquet with rows)")
    members = {a: trials_in(f) for a, f in train.items()}
    owner = {k: u for m in members.values() for u, k in m}
    units = sorted(set(owner.values()))
    orders = {a: spread_order(m, p.seed, angle_name(a), i) for i, (a, m) in enumerate(members.items())}
    steps, notes = ladder({a: len(m) for a, m in members.items()}, p.training_insertions)
    selections = [{a: o[:n] for a, o in orders.items()} for n in steps]
    external = data.frames.get("external", {})
    same = {
        a: kept for a, f in external.items() if len(kept := f[units_of(f).isin(units)].reset_index(drop=True))
    }

    force, more = force_curve(train, same, selections, models, log)
    notes += more
    plan = _Plan()
    same_keys = {a: [k for _, k in trials_in(f)] for a, f in same.items()}
    for i, sel in enumerate(selections):
        if same_keys:
            plan.add(sel, CueScoring(("ladder", i), {"external": same_keys}))
    if not same_keys:
        notes.append(note("cues against training insertions", "no external trial of a training unit"))
    frames = {**data.frames, "train": train}
    calibration, more = _calibration_plan(frames, data.new_units, p, orders, owner, plan)
    notes += more
    if len(train) < 2:
        notes.append(
            note("cues", f"one trained angle ({angle_name(next(iter(train)))}°): nothing to tell apart")
        )
    scored_params = cues.model_copy(update={"kinds": (cue_kind,)})
    found = score_cues(plan.jobs(), frames, data.circuits, scored_params, log) if plan.fits else {}

    ladder_out = [
        {
            "per_angle": n,
            "trials": len(used := [k for keys in sel.values() for k in keys]),
            "by_unit": {u: sum(owner[k] == u for k in used) for u in units},
            "batches": len({b for b, _ in used}),
            "force": force[i],
            "cues": found.get(("ladder", i)),
        }
        for i, (n, sel) in enumerate(zip(steps, selections, strict=True))
    ]
    new, loo = _calibration_figures(calibration, found)
    return {
        "format": FORMAT,
        "params": p.model_dump(mode="json"),
        "cue_within_s": cues.cue_within_s,
        "training": {
            "have_per_angle": {angle_name(a): len(m) for a, m in members.items()},
            "units": units,
            "ladder": steps,
            "subsample": SUBSAMPLE,
            "force_models": [{"name": name, "about": m.about} for name, m in models.items()],
            "force_scored_on": "each angle's external trials of the training units: NRMSE % (eq. 3-4), "
            "the mean over fx, fy, fz and the angles",
            "cues_scored_on": "the training units' external trials, every preset angle: the combined cue "
            "(angle estimate + force check) with the measured force standing in for the model",
            "steps": ladder_out,
        },
        "calibration": {
            "insertions_per_angle": list(p.calibration_insertions),
            "force": "not recomputed: a unit's force against its calibration insertions needs the models "
            "retrained without the unit",
            "new_units": new,
            "leave_one_unit_out": loo,
        },
        "not_computed": notes,
    }
