"""Does a replaced unit keep its angle cues when read through a map? The measurements behind issue 58
(docs/units.md, "A new unit read through a map").

    python benchmarks/bench_cue_map.py PROJECT [PROJECT ...] [--kind lstm]

Each PROJECT is a project kept by `bench_family.py --keep DIR` or `bench_independent.py --keep DIR`
(its `dvc repro` done). For each new unit with a calibration it prints:

1. **Its cues read through a map** (the `kind` model's forces, combined cue, as a trainee sees it:
   balanced accuracy within `cues.cue_within_s` / wrong at the insertion's end / wrong frames / frames
   with a cue, %), with the angle estimator reading the unit's signal (the FSRs' conductance through
   its circuit) as it is, through each model kind's calibration map
   (g' = g Aᵀ + b, `data/calibration/<unit>.json`), and through a map refitted for the cues: the
   3×3 map that brings its calibration insertions' features closest to a shift of the training
   units' layout (Powell, from the identity, a 0.01 pull towards it). Its calibration evidence is
   gathered through the same map. Then, per evidence stage, how far its calibration insertions
   depart from a shift of the training layout over the distance between neighbouring angles
   (`needlecue_runtime.cues.reading.own_departure` / `neighbour_distance`; above 1: "outside"), and how the
   pipeline's rule (`needlecue_runtime.cues.units.cue_reading`) reads it: as it is, or through the map of
   the kind that fits it best where that map removes a departure.
2. **The angle from the force's direction**: exact-angle accuracy of a linear discriminant (shrunk,
   per level) on the unit direction of the force when its norm first reaches each of nine levels (up
   to what 90 % of training trials reach), fitted on the training trials, scored on the external
   trials of the training units (same) and of the new unit (new): from the reference force (the F/T
   sensor, not there at run time: the ceiling) and from the forces the simulator has, each preset
   angle's `kind` model on every angle (the new unit through its calibration), the mean over presets.

The pipeline's figures are not changed by this benchmark: it reads the kept project and writes nothing.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from needlecue_runtime.cues.evidence import UnitMap
from needlecue_runtime.cues.pack import AngleEstimator
from needlecue_runtime.cues.reading import neighbour_distance, own_departure
from needlecue_runtime.cues.units import cue_reading, unit_readings
from needlecue_runtime.vocab import CALIBRATION, angle_name, channels_of
from pipeline.calibration.unit import cue_map_kind
from pipeline.config import CuesParams, load_section
from pipeline.cues.score import evaluate_cues
from pipeline.cues.trials import Trial, replay_evidence, run_evidence, trials_of
from pipeline.cues.unit_evidence import evidence_of, trial_features
from pipeline.dataset.splits import SplitFiles, front_ends, unit_roles
from pipeline.modelling.prediction_store import Predictions

LEVELS = 9  # force-direction levels, as the cue estimator's
REACH = 0.9  # ... up to the force that this share of training trials reach


class Project:
    """What a kept project holds for the cues: params, splits, packs, calibrations, predictions."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self.params = load_section(CuesParams, "cues", root / "params.yaml")
        files = SplitFiles(root / "data" / "processed")
        self.train, self.external = files.by_angle("train"), files.by_angle("external")
        self.circuits = files.front_ends()
        self.roles = unit_roles(root / "data" / "processed")
        packs = sorted((root / "reports" / "cues" / "packs").glob("*.json"))
        self.packs = {float(f.stem): json.loads(f.read_text()) for f in packs}
        if not self.packs:
            raise SystemExit(f"{root}: no reports/cues/packs/*.json (run the project's dvc repro first)")
        self.estimator = next(iter(self.packs.values()))["angle_estimator"]
        self.predictions = Predictions(root / "data" / "predictions")
        cal = root / "data" / "processed" / CALIBRATION
        self.calibration = {float(f.stem): pd.read_parquet(f) for f in sorted(cal.glob("*.parquet"))}
        self.cal_circuits = front_ends(cal)
        self.docs = {
            f.stem: json.loads(f.read_text()) for f in sorted((root / "data" / "calibration").glob("*.json"))
        }
        self.channels = channels_of(next(iter(self.train.values())))

    def new_units(self) -> list[str]:
        return [u for u in self.docs if self.roles.get(u) != "training"]

    def own(self, frames: Mapping[float, pd.DataFrame], unit: str) -> dict[float, pd.DataFrame]:
        return {a: f[f["unit_id"].astype(str) == unit].reset_index(drop=True) for a, f in frames.items()}


# --- 1. the cues through a map -------------------------------------------------------------------


def evidence(project: Project, unit: str, unit_map: UnitMap | None) -> dict[str, Any]:
    """The unit's calibration evidence, gathered through `unit_map`."""
    frames = project.own(project.calibration, unit)
    circuit = {unit: project.cal_circuits.get(unit)}
    maps = None if unit_map is None else {unit: unit_map}
    levels = project.estimator["levels"]
    found, _ = trial_features(frames, project.channels, project.params, circuit, levels, maps)
    return evidence_of(found, len(project.channels)).get(unit, {})


def cues(project: Project, unit: str, unit_map: UnitMap | None, kind: str) -> dict[str, float]:
    """The unit's external trials tracked with its evidence and `unit_map`: what a trainee sees."""
    p = project.params.model_copy(update={"kinds": (kind,)})
    mine = project.own(project.external, unit)

    def forces(k: str, preset: float, a: float) -> np.ndarray | None:
        full = project.predictions.get(k, angle_name(preset), angle_name(a), "external")
        rows = (project.external[a]["unit_id"].astype(str) == unit).to_numpy()
        return None if full is None else full[rows]

    found = evaluate_cues(
        mine,
        p,
        project.packs,
        forces,
        log=lambda _m: None,
        units={unit: evidence(project, unit, unit_map)},
        circuits=project.circuits,
        paper_bound=False,
        maps=None if unit_map is None else {unit: unit_map},
    )
    r = found["results"][kind]["combined"]
    seen = r["seen"]
    return {
        "balanced": 100 * (r["balanced_within_s"] or 0.0),
        "wrong_end": 100 * seen["wrong_final"],
        "wrong_frames": 100 * seen["wrong_frames"],
        "coverage": 100 * seen["coverage_frames"],
    }


def pipeline_reads(project: Project, unit: str) -> str:
    """How the pipeline's rule (`needlecue_runtime.cues.units.cue_reading`) reads the unit: "as it is" or
    "through <kind>'s map" (its calibration's `cues` section as `pipeline.calibration.unit` writes it
    now, whatever the kept project's code wrote)."""
    transforms = project.docs[unit]["transforms"]
    section: dict[str, Any] = {
        "levels": project.estimator["levels"],
        "evidence": evidence(project, unit, None),
    }
    kind = cue_map_kind(transforms) if project.cal_circuits.get(unit) is not None else None
    if kind is not None:
        m = UnitMap.of(transforms[kind])
        section["mapped"] = {"kind": kind, **transforms[kind], "evidence": evidence(project, unit, m)}
    pack = next(iter(project.packs.values()))
    _, unit_map = cue_reading(pack, section)
    return "as it is" if unit_map is None else f"through {kind}'s map"


def departures(project: Project, ev: Mapping[str, Any]) -> list[float]:
    """Per evidence stage, the unit's departure over the neighbouring angles' distance."""
    return departure_ratios(project.estimator, ev)


def departure_ratios(est: Mapping[str, Any], ev: Mapping[str, Any]) -> list[float]:
    """Per evidence stage of the angle estimator `est`, the departure of a unit of evidence `ev` from
    the training layout over the neighbouring angles' distance (above 1: it departs)."""
    out = []
    for j, stage in enumerate(est["stages"]):
        mu, precision = np.asarray(stage["means"]), np.asarray(stage["precision"])
        cells = [
            (c, float(e["n"][j]), np.asarray(e["means"][j]))
            for c, a in enumerate(est["classes_deg"])
            if (e := ev.get(f"{float(a):g}")) and len(e["n"]) > j
        ]
        out.append(own_departure(mu, cells, precision) / neighbour_distance(mu, precision))
    return out


def _prepared(project: Project, unit: str) -> list[tuple[float, np.ndarray, np.ndarray]]:
    """Per calibration trial: (angle, its rest signal, its signal from the contact on)."""
    frames = project.own(project.calibration, unit)
    out = []
    for a in sorted(frames):
        for tr in trials_of(frames[a], project.channels, a, {unit: project.cal_circuits.get(unit)}):
            ev, _ = replay_evidence(tr, project.params, ())
            if ev.contact_t is not None:
                signal = ev.signal(np.maximum(tr.volts[ev.contact_i :], 1e-3))
                out.append((a, np.asarray(ev.signal(ev.rest)), signal))
    return out


def _features(
    prepared: Sequence[tuple], a: np.ndarray, levels: Sequence[float]
) -> list[tuple[float, np.ndarray]]:
    """The estimator's features of each prepared trial through the map `a` (as `Evidence` takes them)."""
    out = []
    for angle, rest, signal in prepared:
        r, s = np.maximum(a @ rest, 1e-3), np.maximum(signal @ a.T, 1e-3)
        loading = np.sqrt(np.sum(np.log(s / r) ** 2, axis=1))
        x = list(np.log(r))
        for level in levels:
            hit = np.flatnonzero(loading >= level)
            if not len(hit):
                break
            d = s[hit[0]] - r
            x.extend(d / (np.linalg.norm(d) or 1.0))
        out.append((angle, np.asarray(x)))
    return out


def refitted_map(project: Project, unit: str) -> UnitMap:
    """The 3×3 map bringing the unit's calibration features closest to a shift of the training
    layout: the sum over evidence stages of its departure over the neighbours' distance."""
    from scipy.optimize import minimize

    est, prepared = project.estimator, _prepared(project, unit)
    classes, n = est["classes_deg"], len(project.channels)

    def loss(theta: np.ndarray) -> float:
        feats = _features(prepared, np.eye(n) + theta.reshape(n, n), est["levels"])
        total = 0.0
        for j, stage in enumerate(est["stages"]):
            mu, precision = np.asarray(stage["means"]), np.asarray(stage["precision"])
            cells = [(classes.index(a), 1.0, x[: n * (j + 1)]) for a, x in feats if len(x) >= n * (j + 1)]
            if len(cells) >= 2:
                shift = np.mean([m - mu[c] for c, _, m in cells], axis=0)
                sq = sum(float((r := m - mu[c] - shift) @ precision @ r) for c, _, m in cells)
                total += sq / mu.shape[1] / (len(cells) - 1) / neighbour_distance(mu, precision)
        return total + 0.01 * float(theta @ theta)

    fit = minimize(loss, np.zeros(n * n), method="Powell", options={"maxfev": 4000, "xtol": 1e-4})
    return UnitMap(np.eye(n) + fit.x.reshape(n, n), np.zeros(n))


# --- 2. the angle from the force's direction -------------------------------------------------------


def _directions(items: Sequence[tuple[Trial, np.ndarray]], p: CuesParams, levels: Sequence[float] | None):
    """(per trial with a contact: (trial, the force's unit direction at each level reached), the levels)."""
    rows, peaks = [], []
    for tr, force in items:
        ev = run_evidence(tr, p)
        if ev.contact_t is None or tr.ins_end < 0:
            continue
        f = force[ev.contact_i : tr.ins_end + 1]
        norm = np.linalg.norm(f, axis=1)
        rows.append((tr, f, norm))
        peaks.append(norm.max())
    if levels is None:
        top = float(np.quantile(peaks, 1 - REACH, method="lower"))
        levels = [top * k / LEVELS for k in range(1, LEVELS + 1)]
    out = []
    for tr, f, norm in rows:
        x: list[float] = []
        for level in levels:
            hit = np.flatnonzero(norm >= level)
            if not len(hit):
                break
            x.extend(f[hit[0]] / norm[hit[0]])
        out.append((tr, np.asarray(x)))
    return out, levels


def direction_accuracy(
    train: Sequence[tuple[Trial, np.ndarray]],
    scored: Mapping[str, Sequence[tuple[Trial, np.ndarray]]],
    p: CuesParams,
    angles: Sequence[float],
    at: Sequence[int],
) -> dict[str, list[float]]:
    """{group: exact-angle accuracy at each level of `at`} of the force-direction discriminant."""
    from sklearn.discriminant_analysis import LinearDiscriminantAnalysis

    fitted, levels = _directions(train, p, None)
    groups = {g: _directions(items, p, levels)[0] for g, items in scored.items()}
    out: dict[str, list[float]] = {g: [] for g in groups}
    for j in at:
        sel = [(tr, x[: 3 * j]) for tr, x in fitted if len(x) >= 3 * j]
        lda = LinearDiscriminantAnalysis(solver="lsqr", shrinkage="auto")
        lda.fit(np.array([x for _, x in sel]), [angles.index(tr.angle) for tr, _ in sel])
        for g, found in groups.items():
            hits = [
                lda.predict(x[None, : 3 * j])[0] == angles.index(tr.angle)
                for tr, x in found
                if len(x) >= 3 * j
            ]
            out[g].append(float(np.mean(hits)) if hits else float("nan"))
    return out


def force_directions(project: Project, kind: str, at: Sequence[int]) -> dict[str, dict[str, list[float]]]:
    """{source: {group: accuracies}}: the reference force's direction, and the preset models'."""
    p, angles = project.params, sorted(project.train)
    train = {a: trials_of(project.train[a], project.channels, a) for a in angles}
    external = {a: trials_of(project.external[a], project.channels, a) for a in sorted(project.external)}

    def group(tr: Trial) -> str:
        return "same" if project.roles.get(tr.unit or "") == "training" else "new"

    scored_ref: dict[str, list] = {}
    for trials in external.values():
        for tr in trials:
            scored_ref.setdefault(group(tr), []).append((tr, tr.force))
    ref = [(tr, tr.force) for trials in train.values() for tr in trials]
    out = {"reference force": direction_accuracy(ref, scored_ref, p, angles, at)}
    per_preset = []
    for preset in angles:

        def pred(a: float, split: str, preset: float = preset) -> np.ndarray:
            return project.predictions.get(kind, angle_name(preset), angle_name(a), split)

        fitted = [(tr, pred(a, "train")[tr.rows]) for a in angles for tr in train[a]]
        scored: dict[str, list] = {}
        for a, trials in external.items():
            forces = pred(a, "external")
            for tr in trials:
                scored.setdefault(group(tr), []).append((tr, forces[tr.rows]))
        per_preset.append(direction_accuracy(fitted, scored, p, angles, at))
    out[f"the preset's {kind} model"] = {
        g: np.nanmean([r[g] for r in per_preset], axis=0).tolist() for g in per_preset[0]
    }
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("projects", type=Path, nargs="+")
    ap.add_argument("--kind", default="lstm")
    args = ap.parse_args()
    at = (1, 3, 5, 9)
    for root in args.projects:
        project = Project(root)
        name = f"{root.parent.name}/{root.name}"
        for unit in project.new_units():
            doc = project.docs[unit]
            variants: dict[str, UnitMap | None] = {"as it is": None}
            for k, t in sorted(doc["transforms"].items()):
                variants[f"{k}'s map" + (" (identity kept)" if "identity_kept" in t else "")] = UnitMap.of(t)
            variants["refitted for the cues"] = refitted_map(project, unit)
            print(
                f"\n{name}, new unit {unit}: cues ({args.kind}) "
                "balanced / wrong end / wrong frames / coverage, %; "
                f"the pipeline (cue_reading) reads it {pipeline_reads(project, unit)}"
            )
            for label, unit_map in variants.items():
                c = cues(project, unit, unit_map, args.kind)
                ev = evidence(project, unit, unit_map)
                est = project.estimator
                away = [
                    j
                    for j, r in enumerate(
                        unit_readings(AngleEstimator.model_validate(est).stages, est["classes_deg"], ev)
                    )
                    if r.departs
                ]
                dep = " ".join(f"{d:.1f}" for d in departures(project, ev))
                print(
                    f"  {label:<32} {c['balanced']:5.1f} / {c['wrong_end']:4.1f} / "
                    f"{c['wrong_frames']:4.2f} / {c['coverage']:5.1f}   departs at {away or 'none'}; "
                    f"departure / neighbours: {dep}"
                )
        print(f"{name}: the angle from the force's direction, exact-angle accuracy at levels {list(at)}")
        for source, groups in force_directions(project, args.kind, at).items():
            line = "; ".join(f"{g} " + " ".join(f"{x:.2f}" for x in acc) for g, acc in sorted(groups.items()))
            print(f"  {source:<24} {line}")


if __name__ == "__main__":
    main()
