"""Scores per estimator unit: how each model does on the units it was trained with, on a new unit
without its calibration, and on the new unit after it (evaluation.json `by_unit`, `unit_transfer`).

Only the external sets are scored here (held-out casts): the training units' held-out trials give the
same-unit figure, a new unit's the new-unit figures. NRMSE follows eq. (4), per unit and angle over
that unit's rows. Small pure functions of (truth, prediction); the report renders them.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from needlecue_runtime.unit_calibration import UnitCalibration
from pipeline.metrics.evaluation import EvalSet
from pipeline.metrics.scores import mean_known, mean_over_axes, nrmse_of, shared_scores
from pipeline.modelling.prediction_store import UNCALIBRATED, Predictions

GROUPS = ("same_unit", "new_uncalibrated", "new_calibrated")


def unit_rows(es: EvalSet) -> dict[str, np.ndarray]:
    """{unit_id: boolean row mask} of one external set (one pseudo-unit "" if it has no unit_id)."""
    if "unit_id" not in es.frame.columns:
        return {"": np.ones(len(es.frame), dtype=bool)}
    units = es.frame["unit_id"].astype(str).to_numpy()
    return {u: units == u for u in sorted(set(units))}


def by_unit(
    eval_sets: Mapping[str, EvalSet],
    predictions: Predictions,
    kinds: Sequence[str],
    roles: Mapping[str, str],
    calibrated: Mapping[str, bool],
    *,
    uncalibrated: bool = False,
) -> dict[str, Any]:
    """unit -> {"role", "calibrated", kind -> angle -> axis -> {rmse, nrmse_pct}}, each model on its own
    angle's external rows of that unit; `uncalibrated` scores the predictions made without the unit's
    calibration (only units that have one)."""
    out: dict[str, Any] = {}
    for angle, es in eval_sets.items():
        if es.source != "external":
            continue
        for unit, mask in unit_rows(es).items():
            cal = bool(calibrated.get(unit, False))
            if uncalibrated and not cal:
                continue
            entry = out.setdefault(unit, {"role": roles.get(unit, "new"), "calibrated": cal})
            for kind in kinds:
                split = UNCALIBRATED if uncalibrated else "external"
                p = predictions.get(kind, angle, angle, split)
                if p is None and uncalibrated:  # this model had no calibration for the unit
                    p = predictions.get(kind, angle, angle, "external")
                if p is None:
                    continue
                axes = predictions.axes(kind, angle)
                entry.setdefault(kind, {})[angle] = shared_scores(p[mask], axes, es.ref[mask], es.axes)
    return out


def _mean_nrmse(per_angle: Mapping[str, Mapping[str, Mapping[str, float]]]) -> float | None:
    return mean_known(mean_over_axes(nrmse_of(s)) for s in per_angle.values())


def group_scores(
    eval_sets: Mapping[str, EvalSet],
    predictions: Predictions,
    kind: str,
    roles: Mapping[str, str],
    calibrated: Mapping[str, bool],
) -> dict[str, dict[str, Any]]:
    """group -> angle -> axis scores for one model kind, each group's units pooled per angle:
    same_unit (training units), new_uncalibrated and new_calibrated (new units that have a calibration,
    without and with it)."""
    out: dict[str, dict[str, Any]] = {g: {} for g in GROUPS}
    for angle, es in eval_sets.items():
        if es.source != "external":
            continue
        masks = unit_rows(es)
        same = np.zeros(len(es.frame), bool)
        new = np.zeros(len(es.frame), bool)
        for unit, mask in masks.items():
            if roles.get(unit, "new") == "training":
                same |= mask
            elif calibrated.get(unit, False):
                new |= mask
        cal = predictions.get(kind, angle, angle, "external")
        raw = predictions.get(kind, angle, angle, UNCALIBRATED)
        if cal is None:
            continue
        axes = predictions.axes(kind, angle)
        if same.any():
            out["same_unit"][angle] = shared_scores(cal[same], axes, es.ref[same], es.axes)
        if new.any():
            out["new_calibrated"][angle] = shared_scores(cal[new], axes, es.ref[new], es.axes)
            raw_new = (cal if raw is None else raw)[new]
            out["new_uncalibrated"][angle] = shared_scores(raw_new, axes, es.ref[new], es.axes)
    return out


def unit_transfer(
    eval_sets: Mapping[str, EvalSet],
    predictions: Predictions,
    kinds: Sequence[str],
    roles: Mapping[str, str],
    calibrated: Mapping[str, bool],
    champions: Mapping[str, str],
) -> dict[str, Any]:
    """kind | "champion" -> {group: mean NRMSE % over angles, "ratio": new_calibrated / same_unit};
    the champion row takes, per angle, the kind in `champions` ({angle: kind})."""
    groups = {k: group_scores(eval_sets, predictions, k, roles, calibrated) for k in kinds}
    rows: dict[str, Any] = {}
    for kind, g in groups.items():
        rows[kind] = {name: _mean_nrmse(g[name]) for name in GROUPS}
    champ = {
        name: {a: groups[k][name][a] for a, k in champions.items() if k in groups and a in groups[k][name]}
        for name in GROUPS
    }
    rows["champion"] = {name: _mean_nrmse(champ[name]) for name in GROUPS}
    rows["champion"]["kinds"] = dict(sorted(champions.items(), key=lambda kv: float(kv[0])))
    for row in rows.values():
        same, new = row["same_unit"], row["new_calibrated"]
        row["ratio"] = None if same is None or new is None or same == 0 else new / same
    return rows


def champions_by_angle(within: Mapping[str, Mapping[str, Any]], kinds: Sequence[str]) -> dict[str, str]:
    """Per angle, the kind with the lowest mean external NRMSE (ties: the simpler kind)."""
    best: dict[str, tuple[float, int, str]] = {}
    for rank, kind in enumerate(kinds):
        for angle, s in within.get(kind, {}).items():
            m = mean_over_axes(nrmse_of(s))
            if m is not None and (angle not in best or (m, rank) < best[angle][:2]):
                best[angle] = (m, rank, kind)
    return {a: v[2] for a, v in best.items()}


def calibration_summary(units: Mapping[str, UnitCalibration]) -> dict[str, Any]:
    """unit -> what its calibration used and did (from the calibrate stage's documents)."""
    return {
        unit: {
            "batches": doc.batches,
            "n_trials": len(doc.trials),
            "angles_used": doc.angles_used,
            "angles_missing": doc.angles_missing,
            "set_aside": [f"{s.file}: {s.reason}" for s in doc.set_aside],
            "loss": {
                kind: {"before": t.loss_before, "after": t.loss_after, "identity_kept": t.identity_kept}
                for kind, t in sorted(doc.transforms.items())
            },
        }
        for unit, doc in sorted(units.items())
    }
