"""The report's "Estimator units" section: each model on the units it was trained with, on a new
unit without its calibration and after it (force and cues), and what each calibration used. Data in:
evaluation.json (`unit_transfer`, `by_unit`, `calibration`) and the cue evaluation (`by_unit_group`)."""

from __future__ import annotations

from collections.abc import Mapping

from pipeline.cues.document import CueEvaluation, GroupResult, Seen, UnitGroup
from pipeline.metrics.document import CalibrationSummary, Evaluation, TransferRow, UnitScores
from pipeline.metrics.scores import mean_known, mean_over_axes
from pipeline.modelling.kinds import kind_label
from pipeline.reporting.style import fmt, table

# Targets for a new unit after one short calibration (issue 12), measured on the data at hand.
NEW_UNIT_RATIO = 1.2  # champion NRMSE on the calibrated new unit / on the training units
CUE_BALANCED = 0.95  # balanced accuracy of the cues on the calibrated new unit, within cue_within_s
UNCALIBRATED_RATIO = 1.5  # champion NRMSE on the new unit without its calibration / on the training units
MAX_WRONG = (
    0.02  # wrong angle cues a trainee may see: at the insertion's end and per insertion frame (issue 39)
)
MISSING = "missing"

GROUP_LABELS = {
    "same_unit": "same unit",
    "new_uncalibrated": "new unit, uncalibrated",
    "new_calibrated": "new unit, calibrated",
}
# why a group's figure can be missing: which external trials it needs
NEEDS = {
    "same_unit": "no external trial of a training unit",
    "new_uncalibrated": "no external trial of a new unit with a calibration",
    "new_calibrated": "no external trial of a new unit with a calibration",
}


def _mark(ok: bool | None) -> str:
    return "" if ok is None else (" ✓" if ok else " ✗")


def _value(x: float | None, spec: str, unit: str, why: str) -> str:
    """A figure with its unit, or what is missing and why: never a bare unit."""
    return f"{MISSING} ({why})" if x is None else f"{format(x, spec)}{unit}"


def force_table(transfer: Mapping[str, TransferRow]) -> list[str]:
    rows = []
    for kind, r in transfer.items():
        label = "**champion**" if kind == "champion" else kind_label(kind)
        cells = [fmt(getattr(r, g), ".2f") or "–" for g in GROUP_LABELS]
        rows.append([label, *cells, fmt(r.ratio, ".2f") or "–"])
    header = ["model", *(f"{g} (%)" for g in GROUP_LABELS.values()), "new calibrated / same"]
    return table(header, rows)


def _ratio(a: float | None, b: float | None) -> float | None:
    return None if a is None or b is None or b == 0 else a / b


def targets(transfer: Mapping[str, TransferRow], cue_groups: Mapping[str, UnitGroup]) -> list[str]:
    """The targets' lines, every figure from this run's metrics; a figure the data cannot give reads
    as missing, with the trials it would need."""
    champ = transfer.get("champion")
    same, uncal, cal = (
        (None, None, None)
        if champ is None
        else (
            champ.same_unit,
            champ.new_uncalibrated,
            champ.new_calibrated,
        )
    )
    ratio = _ratio(cal, same)
    raw_ratio = _ratio(uncal, same)
    kinds = {k: r.same_unit for k, r in transfer.items() if k != "champion" and r.same_unit is not None}
    best_kind = min(kinds, key=lambda k: kinds[k]) if kinds else None
    why_ratio = NEEDS["same_unit"] if same is None else NEEDS["new_calibrated"]
    lines = [
        "- Same unit (the training units' external trials): champion NRMSE "
        + _value(same, ".2f", " %", NEEDS["same_unit"])
        + (
            f"; the best one kind of model at every angle, {kind_label(best_kind)}, {kinds[best_kind]:.2f} %"
            if best_kind is not None
            else ""
        ),
        f"- New unit after calibration, champion NRMSE at most {NEW_UNIT_RATIO:g}× the same-unit figure: "
        + _value(ratio, ".2f", "×", why_ratio)
        + _mark(None if ratio is None else ratio <= NEW_UNIT_RATIO),
        f"- New unit without its calibration, champion NRMSE (reported; at most {UNCALIBRATED_RATIO:g}× "
        "where the front end is declared): " + _value(raw_ratio, ".2f", "× the same-unit figure", why_ratio),
    ]
    best = best_cue(cue_groups.get("new_calibrated"))
    cue_line = (
        "- Cues on the calibrated new unit, balanced accuracy within the window at least "
        f"{CUE_BALANCED:.0%}: "
    )
    if best is None:
        lines.append(cue_line + f"{MISSING} (no cue scored on a calibrated new unit's external trials)")
    else:
        kind, method, value = best
        lines.append(
            cue_line + f"best {value:.1%} ({kind_label(kind)}, {method}){_mark(value >= CUE_BALANCED)}"
        )
    lines += _wrong_lines(cue_groups)
    return lines


def _results(group: UnitGroup | None) -> dict[str, dict[str, GroupResult]]:
    return {} if group is None else group.results


def _wrong_lines(cue_groups: Mapping[str, UnitGroup]) -> list[str]:
    """Per unit group, the combined cue's wrong cues against MAX_WRONG (the worst model kind's)."""
    out = []
    for group, label in GROUP_LABELS.items():
        seen = [
            r.seen
            for kind, methods in _results(cue_groups.get(group)).items()
            if kind != "reference"
            for method, r in methods.items()
            if method == "combined"
        ]
        if not seen:
            continue
        end = max(s.wrong_final or 0.0 for s in seen)
        frames = max(s.wrong_frames or 0.0 for s in seen)
        cover = min(s.coverage_frames or 0.0 for s in seen)
        out.append(
            f"- Cues, {label}: a wrong cue at the insertion's end in at most {MAX_WRONG:.0%} of trials and "
            f"of insertion frames: {end:.1%} and {frames:.1%}{_mark(max(end, frames) <= MAX_WRONG)} "
            f"(a cue shown in {cover:.1%} of insertion frames)"
        )
    return out


def best_cue(group: UnitGroup | None) -> tuple[str, str, float] | None:
    """(kind, method, balanced accuracy within the window) of the best deployable cue in a group."""
    found = [
        (r.balanced_within_s, kind, method)
        for kind, methods in _results(group).items()
        if kind != "reference"
        for method, r in methods.items()
        if r.balanced_within_s is not None
    ]
    if not found:
        return None
    value, kind, method = max(found)
    return kind, method, value


def _seen_cell(seen: Seen) -> str:
    pct = {k: 100 * (getattr(seen, k) or 0.0) for k in ("wrong_final", "wrong_frames", "coverage_frames")}
    return f"wrong {pct['wrong_final']:.1f} / {pct['wrong_frames']:.1f} %; cue {pct['coverage_frames']:.0f} %"


def cue_table(cue_groups: Mapping[str, UnitGroup]) -> list[str]:
    kinds = sorted(
        {(k, m) for g in cue_groups.values() for k, ms in g.results.items() for m in ms},
        key=lambda km: (km[0] == "reference", km),
    )
    results = [r for g in cue_groups.values() for ms in g.results.values() for r in ms.values()]
    within = results[0].within_s if results else 3.0
    rows = []
    for kind, method in kinds:
        cells = []
        for group in GROUP_LABELS:
            r = _results(cue_groups.get(group)).get(kind, {}).get(method)
            v = None if r is None else r.balanced_within_s
            cells.append("–" if r is None or v is None else f"{v:.1%}; {_seen_cell(r.seen)}")
        rows.append([f"{kind_label(kind)} {method}", *cells])
    header = ["cue (model, method)", *(GROUP_LABELS[g] for g in GROUP_LABELS)]
    return [
        f"Balanced accuracy over continue / correct / stop of the cue being right, and staying right, within "
        f"{within:g} s of the insertion's start (external trials; chance is 33 %); then the wrong cues "
        "shown at the insertion's end and per insertion frame, and the share of insertion frames with a "
        "cue at all (the rest say *no angle cue*):",
        "",
        *table(header, rows),
    ]


def unit_table(by_unit: Mapping[str, UnitScores], by_unit_uncal: Mapping[str, UnitScores]) -> list[str]:
    kinds = sorted({k for u in by_unit.values() for k in u.kinds()})
    rows = []
    for unit, entry in sorted(by_unit.items()):
        cells = []
        for kind in kinds:
            per_angle = entry.kind(kind)
            m = mean_known(mean_over_axes({a: v.nrmse_pct for a, v in s.items()}) for s in per_angle.values())
            raw = by_unit_uncal[unit].kind(kind) if unit in by_unit_uncal else {}
            r = mean_known(mean_over_axes({a: v.nrmse_pct for a, v in s.items()}) for s in raw.values())
            cells.append(fmt(m, ".2f") + ("" if not raw else f" ({fmt(r, '.2f')} uncalibrated)"))
        rows.append([unit, entry.role, "yes" if entry.calibrated else "no", *cells])
    return table(["unit", "role", "calibrated", *(f"{kind_label(k)} (%)" for k in kinds)], rows)


def calibration_table(calibration: Mapping[str, CalibrationSummary]) -> list[str]:
    out: list[str] = []
    for unit, c in sorted(calibration.items()):
        used = ", ".join(f"{a}°" for a in c.angles_used) or "none"
        missing = c.angles_missing
        n_all = len(c.angles_used) + len(missing)
        note = (
            f"; **calibrated on {len(c.angles_used)} of {n_all} angles**, none at "
            + ", ".join(f"{a}°" for a in missing)
            if missing
            else ""
        )
        batches = ", ".join(c.batches) or "–"
        out.append(f"- **{unit}**: {c.n_trials} trial(s) from {batches} at {used}{note}.")
        for kind, loss in c.loss.items():
            kept = f" (identity kept: {loss.identity_kept})" if loss.identity_kept else ""
            before, after = fmt(loss.before, ".4f"), fmt(loss.after, ".4f")
            out.append(f"  - {kind_label(kind)}: loss {before} → {after}{kept}")
        for s in c.set_aside:
            out.append(f"  - set aside: {s}")
    return out or ["No unit has a calibration batch (`purpose: calibration`)."]


def estimator_units(metrics: Evaluation, cue_eval: CueEvaluation | None) -> str:
    """The section's Markdown ("" when evaluation.json has no per-unit scores)."""
    transfer = metrics.unit_transfer
    if not transfer:
        return ""
    cue_groups = (None if cue_eval is None else cue_eval.by_unit_group) or {}
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
        *unit_table(metrics.by_unit, metrics.by_unit_uncalibrated),
        "",
    ]
    if cue_groups:
        out += ["### Cues per unit group", "", *cue_table(cue_groups), ""]
    out += ["### Calibrations", "", *calibration_table(metrics.calibration), ""]
    return "\n".join(out)
