"""One unit's calibration document (format "needlecue-unit/4"), from its calibration rows and the
frozen shared models: which trials and angles it used, what was set aside and why, and per model kind
the input transform with the models it was fitted through (their checkpoint hashes: a transform
applies to those models only).

    {"format", "unit_id", "batches", "trials": [{batch_id, trial_id, angle}], "angles_used",
     "angles_missing", "set_aside": [{batch_id, trial_id, file, angle, reason}],
     "transforms": {kind: {"matrix", "offset", "fitted_through": [angle], "models": {angle: sha},
                           "loss_before", "loss_after", "loss_after_by_angle", "identity_kept"?}},
     "params": {...}, "cues": {"levels": [loading levels],
     "evidence": {angle: {"n": [per stage], "means": [per stage]}},
     "mapped"?: {"kind", "matrix", "offset", "evidence"}}}

`cues.mapped` is the same evidence gathered through the unit's map on its conductance (`cue_map_kind`
says whose); the cues read the unit through it only where that removes a departure from the
training units' layout (`needlecue_runtime.cues.units.cue_reading`).

The stage and `needlecue calibrate` both build it here; `needlecue_runtime.unit_calibration` reads it.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import pandas as pd

from needlecue_runtime.cues.evidence import UnitMap
from needlecue_runtime.frontend import Circuit
from needlecue_runtime.unit_calibration import DIGITS, FORMAT
from needlecue_runtime.vocab import angle_name, jsonable, sorted_angles
from pipeline.calibration.fit import AngleData, fit_transforms
from pipeline.config import CalibrateParams, CuesParams
from pipeline.cues.unit_evidence import evidence_of, trial_features
from pipeline.logs import Log
from pipeline.modelling.checkpoint import checkpoint_sha256
from pipeline.modelling.predictor import Predictor


def _set_aside(batch: Any, trial: Any, angle: str, reason: str) -> dict[str, str]:
    """One calibration trial set aside, located by its batch, trial and estimator file."""
    return {
        "batch_id": str(batch),
        "trial_id": str(trial),
        "file": f"{batch}/{trial}.fsr.csv",
        "angle": angle,
        "reason": reason,
    }


def _trial_problems(frame: pd.DataFrame, p: CalibrateParams) -> list[dict[str, str]]:
    """Calibration trials that cannot calibrate anything, with the reason."""
    out = []
    for (batch, trial), rows in frame.groupby(["batch_id", "trial_id"], sort=True):
        span = float(rows["t_s"].max() - rows["t_s"].min()) if len(rows) > 1 else 0.0
        if span < p.min_trial_s:
            reason = (
                f"{span:.1f} s of aligned samples, a calibration insertion needs "
                f"calibrate.min_trial_s = {p.min_trial_s:g} s"
            )
            out.append(_set_aside(batch, trial, angle_name(rows["angle_deg"].iloc[0]), reason))
    return out


def calibrate_unit(
    unit_id: str,
    rows: pd.DataFrame,
    models: Mapping[str, Mapping[str, Predictor]],
    trained_angles: list[str],
    p: CalibrateParams,
    log: Log | None = None,
    cues: CuesParams | None = None,
    front_end: Circuit | None = None,
    cue_levels: Sequence[float] = (),
    workers: int = 1,
) -> dict[str, Any]:
    """The calibration document of `unit_id` from its calibration `rows` (processed frame, any angles)
    through `models` ({kind: {angle: Predictor}}), for a pipeline trained at `trained_angles`; with
    `cues`, also what its calibration insertions tell the cue packs' angle estimator (its evidence,
    `pipeline.cues.unit_evidence`, gathered at the angle estimator's loading levels `cue_levels`, from
    `training_levels`). `front_end` is the circuit the unit's batches declare: its rows are read
    through it, and the document carries it for the simulator's client. The transforms' fits run on
    up to `workers` processes (the same document on any number)."""
    log = log or (lambda _m: None)
    set_aside = _trial_problems(rows, p)
    bad = {(s["batch_id"], s["trial_id"]) for s in set_aside}
    keys = list(zip(rows["batch_id"], rows["trial_id"], strict=True))
    used = rows[[k not in bad for k in keys]]
    by_angle = {angle_name(a): f for a, f in used.groupby("angle_deg", sort=True)}
    for angle in sorted_angles(by_angle):
        if angle not in trained_angles:
            reason = f"no shared model is trained at {angle}° (train.angles)"
            for (batch, trial), _ in by_angle[angle].groupby(["batch_id", "trial_id"], sort=True):
                set_aside.append(_set_aside(batch, trial, angle, reason))
            del by_angle[angle]
    angles = sorted_angles(by_angle)
    trials = sorted(
        {
            (str(b), str(t), a)
            for a, f in by_angle.items()
            for b, t in zip(f["batch_id"], f["trial_id"], strict=True)
        }
    )
    doc: dict[str, Any] = {
        "format": FORMAT,
        "unit_id": unit_id,
        "batches": sorted({b for b, _, _ in trials}),
        "trials": [{"batch_id": b, "trial_id": t, "angle": a} for b, t, a in trials],
        "angles_used": angles,
        "angles_missing": [a for a in trained_angles if a not in by_angle],
        "set_aside": sorted(set_aside, key=lambda s: (s["batch_id"], s["trial_id"])),
        "transforms": {},
        "params": p.model_dump(mode="json"),
        "front_end": None if front_end is None else front_end.model_dump(mode="json"),
    }
    fit_angles = {kind: [a for a in angles if a in ms] for kind, ms in models.items()}
    fit_angles = {kind: found for kind, found in fit_angles.items() if found}
    data = {
        kind: [AngleData.of(models[kind][a], by_angle[a], front_end) for a in found]
        for kind, found in fit_angles.items()
    }
    for kind, (transform, report) in fit_transforms(data, p, workers=workers).items():
        doc["transforms"][kind] = {
            **transform.to_dict(),
            "fitted_through": fit_angles[kind],
            # the models it applies to: those of this kind at every angle, calibrated or not (one
            # transform serves the unit), each named by its checkpoint hash
            "models": {a: checkpoint_sha256(m.checkpoint) for a, m in sorted(models[kind].items())},
            **report,
        }
        kept = f", identity kept: {report['identity_kept']}" if "identity_kept" in report else ""
        log(
            f"{unit_id}: {kind} through {len(fit_angles[kind])} angle(s): loss "
            f"{report['loss_before']:.4f} -> {report['loss_after']:.4f}{kept}"
        )
    if cues is not None:
        doc["cues"] = cue_evidence(unit_id, by_angle, models, cues, front_end, cue_levels, doc["transforms"])
    return jsonable(doc, DIGITS)


def cue_map_kind(transforms: Mapping[str, Mapping[str, Any]]) -> str | None:
    """The model kind whose map on the conductance fits the unit best: the lowest loss on the angles
    left out (else on all), among the maps its calibration kept (not the identity); None if none."""
    found = [
        (t.get("held_out_loss_after", t["loss_after"]), kind)
        for kind, t in sorted(transforms.items())
        if t.get("domain") == "conductance" and "identity_kept" not in t
    ]
    return min(found)[1] if found else None


def cue_evidence(
    unit_id: str,
    by_angle: Mapping[str, pd.DataFrame],
    models: Mapping[str, Mapping[str, Predictor]],
    cues: CuesParams,
    front_end: Circuit | None,
    levels: Sequence[float],
    transforms: Mapping[str, Mapping[str, Any]],
) -> dict[str, Any]:
    """The document's `cues` section: the unit's evidence for the angle estimator, read as it is and,
    where its circuit is declared and a map was kept, through the map of `cue_map_kind` (as stored:
    rounded as the document keeps it, so that the simulator reading the stored map sees the same)."""
    channels = next((list(m.channels) for ms in models.values() for m in ms.values()), None)
    if not channels:
        return {"levels": list(levels), "evidence": {}}
    frames = {float(a): f for a, f in by_angle.items()}
    circuit = {unit_id: front_end}

    def evidence(maps: Mapping[str, UnitMap] | None) -> dict[str, Any]:
        trials = trial_features(frames, channels, cues, circuit, levels, maps)[0]
        return evidence_of(trials, len(channels)).get(unit_id, {})

    out: dict[str, Any] = {"levels": list(levels), "evidence": evidence(None)}
    kind = cue_map_kind(transforms)
    if kind is not None:
        stored = jsonable({k: transforms[kind][k] for k in ("matrix", "offset")}, DIGITS)
        out["mapped"] = {"kind": kind, **stored, "evidence": evidence({unit_id: UnitMap.of(stored)})}
    return out
