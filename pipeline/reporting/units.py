"""The report's "Estimator units" section: each model on the units it was trained with, on a new
unit without its calibration and after it (force and cues), and what each calibration used. Data in:
metrics.json (`unit_transfer`, `by_unit`, `calibration`) and the cue evaluation (`by_unit_group`)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from pipeline.metrics.scores import mean_known, mean_over_axes
from pipeline.reporting.style import fmt, table
from pipeline.vocab import AXES, kind_label

# Targets of issue 12 (a new unit after one short calibration), checked on the defaults.
NEW_UNIT_RATIO = 1.2  # champion NRMSE on the calibrated new unit / on the training units
CUE_BALANCED = 0.95  # balanced accuracy of the cues on the calibrated new unit, within cue_within_s
SAME_UNIT_BASELINE_PCT = 3.2  # champion NRMSE on the external sets before units were introduced
SAME_UNIT_TOLERANCE = 0.10

GROUP_LABELS = {
    "same_unit": "same unit",
    "new_uncalibrated": "new unit, uncalibrated",
    "new_calibrated": "new unit, calibrated",
}


def _mark(ok: bool | None) -> str:
    return "" if ok is None else (" ✓" if ok else " ✗")


def force_table(transfer: Mapping[str, Any]) -> list[str]:
    rows = []
    for kind, r in transfer.items():
        label = "**champion**" if kind == "champion" else kind_label(kind)
        rows.append([label, *(fmt(r.get(g), ".2f") for g in GROUP_LABELS), fmt(r.get("ratio"), ".2f")])
    header = ["model", *(f"{g} (%)" for g in GROUP_LABELS.values()), "new calibrated / same"]
    return table(header, rows)


def targets(transfer: Mapping[str, Any], cue_groups: Mapping[str, Any]) -> list[str]:
    champ = transfer.get("champion") or {}
    ratio, same = champ.get("ratio"), champ.get("same_unit")
    limit = SAME_UNIT_BASELINE_PCT * (1 + SAME_UNIT_TOLERANCE)
    best = best_cue(cue_groups.get("new_calibrated") or {})
    ratio_ok = None if ratio is None else ratio <= NEW_UNIT_RATIO
    same_ok = None if same is None else same <= limit
    lines = [
        f"- New unit after calibration, champion NRMSE at most {NEW_UNIT_RATIO:g}× the same-unit "
        f"figure: {fmt(ratio, '.2f')}×{_mark(ratio_ok)}",
        f"- Same-unit champion NRMSE within {SAME_UNIT_TOLERANCE:.0%} of the {SAME_UNIT_BASELINE_PCT:g} % "
        f"before units (at most {limit:.2f} %): {fmt(same, '.2f')} %{_mark(same_ok)}",
    ]
    if best is not None:
        kind, method, value = best
        lines.append(
            f"- Cues on the calibrated new unit, balanced accuracy within the window at least "
            f"{CUE_BALANCED:.0%}: best {value:.1%} ({kind_label(kind)}, {method})"
            f"{_mark(value >= CUE_BALANCED)}"
        )
    return lines


def best_cue(group: Mapping[str, Any]) -> tuple[str, str, float] | None:
    """(kind, method, balanced accuracy within the window) of the best deployable cue in a group."""
    found = [
        (r["balanced_within_s"], kind, method)
        for kind, methods in (group.get("results") or {}).items()
        if kind != "reference"
        for method, r in methods.items()
        if r.get("balanced_within_s") is not None
    ]
    if not found:
        return None
    value, kind, method = max(found)
    return kind, method, value


def cue_table(cue_groups: Mapping[str, Any]) -> list[str]:
    kinds = sorted(
        {(k, m) for g in cue_groups.values() for k, ms in (g.get("results") or {}).items() for m in ms},
        key=lambda km: (km[0] == "reference", km),
    )
    within = next(
        (
            r.get("within_s")
            for g in cue_groups.values()
            for ms in (g.get("results") or {}).values()
            for r in ms.values()
        ),
        3.0,
    )
    rows = []
    for kind, method in kinds:
        cells = []
        for group in GROUP_LABELS:
            r = ((cue_groups.get(group) or {}).get("results") or {}).get(kind, {}).get(method)
            v = None if r is None else r.get("balanced_within_s")
            cells.append("–" if v is None else f"{v:.1%}")
        rows.append([f"{kind_label(kind)} {method}", *cells])
    header = ["cue (model, method)", *(GROUP_LABELS[g] for g in GROUP_LABELS)]
    return [
        f"Balanced accuracy over continue / correct / stop of the cue being right, and staying right, within "
        f"{within:g} s of the insertion's start (external trials; chance is 33 %):",
        "",
        *table(header, rows),
    ]


def unit_table(by_unit: Mapping[str, Any], by_unit_uncal: Mapping[str, Any]) -> list[str]:
    kinds = sorted({k for u in by_unit.values() for k in u if k not in ("role", "calibrated")})
    rows = []
    for unit, entry in sorted(by_unit.items()):
        cells = []
        for kind in kinds:
            per_angle = entry.get(kind, {})
            m = mean_known(mean_over_axes({a: s[a]["nrmse_pct"] for a in AXES}) for s in per_angle.values())
            raw = by_unit_uncal.get(unit, {}).get(kind, {})
            r = mean_known(mean_over_axes({a: s[a]["nrmse_pct"] for a in AXES}) for s in raw.values())
            cells.append(fmt(m, ".2f") + ("" if not raw else f" ({fmt(r, '.2f')} uncalibrated)"))
        rows.append([unit, entry.get("role", "?"), "yes" if entry.get("calibrated") else "no", *cells])
    return table(["unit", "role", "calibrated", *(f"{kind_label(k)} (%)" for k in kinds)], rows)


def calibration_table(calibration: Mapping[str, Any]) -> list[str]:
    out: list[str] = []
    for unit, c in sorted(calibration.items()):
        used = ", ".join(f"{a}°" for a in c.get("angles_used", [])) or "none"
        missing = c.get("angles_missing") or []
        n_all = len(c.get("angles_used", [])) + len(missing)
        note = (
            f"; **calibrated on {len(c.get('angles_used', []))} of {n_all} angles**, none at "
            + ", ".join(f"{a}°" for a in missing)
            if missing
            else ""
        )
        batches = ", ".join(c.get("batches", [])) or "–"
        out.append(f"- **{unit}**: {c.get('n_trials', 0)} trial(s) from {batches} at {used}{note}.")
        for kind, loss in (c.get("loss") or {}).items():
            kept = f" (identity kept: {loss['identity_kept']})" if loss.get("identity_kept") else ""
            before, after = fmt(loss.get("before"), ".4f"), fmt(loss.get("after"), ".4f")
            out.append(f"  - {kind_label(kind)}: loss {before} → {after}{kept}")
        for s in c.get("set_aside", []):
            out.append(f"  - set aside: {s}")
    return out or ["No unit has a calibration batch (`purpose: calibration`)."]


def estimator_units(metrics: Mapping[str, Any], cue_eval: Mapping[str, Any] | None) -> str:
    """The section's Markdown ("" when metrics.json has no per-unit scores)."""
    transfer = metrics.get("unit_transfer") or {}
    if not transfer:
        return ""
    cue_groups = (cue_eval or {}).get("by_unit_group") or {}
    out = [
        "## Estimator units: same unit, new unit, after calibration",
        "",
        "Every estimator unit differs (FSR gain, cast-in preload, placement, drift: docs/physics.md). The "
        "shared models are trained on several units; a new unit is scored on its own held-out cast, without "
        "and with the calibration fitted from its calibration batch (one short insertion per angle; "
        "docs/units.md explains the inputs and the calibration, and what was tried).",
        "",
        "### Targets",
        "",
        *targets(transfer, cue_groups),
        "",
        "### Force: mean NRMSE over angles and axes (external sets)",
        "",
        "The champion row takes, per angle, the model with the lowest external NRMSE.",
        "",
        *force_table(transfer),
        "",
        "### Per unit",
        "",
        *unit_table(metrics.get("by_unit") or {}, metrics.get("by_unit_uncalibrated") or {}),
        "",
    ]
    if cue_groups:
        out += ["### Cues per unit group", "", *cue_table(cue_groups), ""]
    out += ["### Calibrations", "", *calibration_table(metrics.get("calibration") or {}), ""]
    return "\n".join(out)
