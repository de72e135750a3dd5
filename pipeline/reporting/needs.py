"""How much data a lab needs, in the report: the `## How much data you need` section and its figure,
rendered from the needs stage's needs.json (`pipeline.needs`)."""

from __future__ import annotations

import textwrap
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from pipeline.reporting.style import COLORS, fmt, save_png, table

FORCE_NAMES = {"ls": "LS", "fnn_stand_in": "networks' stand-in"}
FORCE_COLORS = {"ls": COLORS["ls"], "fnn_stand_in": COLORS["fnn"]}


def _pct(x: float | None) -> str:
    return "–" if x is None else f"{100 * x:.1f} %"


def _cue_cells(figures: Mapping[str, Any] | None) -> list[str]:
    """Balanced within the cue time, and what the trainee sees: wrong at the end, wrong frames, frames
    with a cue; or why there is nothing."""
    if not figures:
        return ["–"] * 4
    if "unavailable" in figures:
        return [f"not scored: {figures['unavailable']}", "", "", ""]
    seen = figures.get("seen") or {}
    return [
        _pct(figures.get("balanced_within_s")),
        *(_pct(seen.get(k)) for k in ("wrong_final", "wrong_frames", "coverage_frames")),
    ]


def _cue_header(within_s: float) -> list[str]:
    return [f"cues: balanced within {within_s:g} s", "wrong at the end", "wrong frames", "frames with a cue"]


def training_table(needs: Mapping[str, Any]) -> list[str]:
    """One row per step of the ladder: its trials, each force model's mean NRMSE, the cues."""
    training = needs["training"]
    models = [m["name"] for m in training.get("force_models") or []]
    header = [
        "insertions per angle",
        "trials (per unit)",
        *(f"{FORCE_NAMES.get(m, m)}: NRMSE %" for m in models),
        *_cue_header(float(needs["cue_within_s"])),
    ]
    rows = []
    for s in training["steps"]:
        units = ", ".join(str(n) for n in s["by_unit"].values())
        force = [
            fmt(((s.get("force") or {}).get(m) or {}).get("mean_nrmse_pct"), ".2f") or "–" for m in models
        ]
        rows.append([str(s["per_angle"]), f"{s['trials']} ({units})", *force, *_cue_cells(s.get("cues"))])
    return table(header, rows)


def calibration_table(needs: Mapping[str, Any]) -> list[str]:
    """One row per unit and k: each training unit left out, their mean, each new unit."""
    cal = needs["calibration"]
    rows = []
    loo = cal.get("leave_one_unit_out") or {}
    for unit, entry in (loo.get("units") or {}).items():
        for s in entry["steps"]:
            rows.append([f"{unit} (left out)", str(s["k"]), str(entry["test_trials"]), *_cue_cells(s)])
    for m in loo.get("mean") or []:
        rows.append([f"**mean of {m['units']} left out**", str(m["k"]), "", *_cue_cells(m)])
    for unit, entry in (cal.get("new_units") or {}).items():
        for s in entry["steps"]:
            rows.append([f"{unit} (new unit)", str(s["k"]), str(s.get("trials", "")), *_cue_cells(s)])
    if not rows:
        return []
    header = [
        "unit",
        "calibration insertions per angle",
        "trials scored",
        *_cue_header(float(needs["cue_within_s"])),
    ]
    return table(header, rows)


def how_much_data_you_need(needs: Mapping[str, Any], figure: str = "needs/needs.png") -> str:
    """The `## How much data you need` section (the figure's link relative to `reports/`)."""
    training, cal = needs["training"], needs["calibration"]
    have = training["have_per_angle"]
    models = "; ".join(m["about"] for m in training["force_models"])
    per_angle = ", ".join(f"{a}°: {n}" for a, n in have.items())
    lines = [
        "## How much data you need",
        "",
        "From this lab's own data, subsampled (the `needs` stage): force and angle-cue figures against the "
        "training insertions per angle, and the cues against a new unit's calibration insertions per angle. "
        f"Training insertions per angle here: {per_angle}. The subsamples take, {training['subsample']}. "
        f"The force figures are those of models refitted on each subsample ({models or 'none built'}), "
        f"not of the trained LSTM, scored on {training['force_scored_on']}. The cues: "
        f"{training['cues_scored_on']}. Force against calibration insertions is {cal['force']}.",
        "",
        "**What to record next**",
        "",
        *(f"- {s}" for s in needs.get("advice") or ["(no advice: nothing could be computed)"]),
        "",
        "### Training insertions per angle",
        "",
        *training_table(needs),
        "",
    ]
    cal_rows = calibration_table(needs)
    if cal_rows:
        lines += ["### Calibration insertions per angle", "", *cal_rows, ""]
    if needs.get("not_computed"):
        lines += ["Not computed, and why:", ""]
        lines += [f"- {n['what']}: {n['why']}" for n in needs["not_computed"]]
        lines.append("")
    lines += [f"![Force and cue figures against the insertions per angle]({figure})", ""]
    return "\n".join(lines)


def _series(steps: Sequence[Mapping[str, Any]], x: str, get: Any) -> tuple[list[int], list[float]]:
    xs, ys = [], []
    for s in steps:
        v = get(s)
        if v is not None:
            xs.append(int(s[x]))
            ys.append(float(v))
    return xs, ys


def _nothing(ax: Any, why: str) -> None:
    ax.text(0.5, 0.5, textwrap.fill(why, 40), ha="center", va="center", fontsize=8, transform=ax.transAxes)
    ax.set_xticks([])
    ax.set_yticks([])


def plot_needs(needs: Mapping[str, Any], path: Path) -> None:
    """Three panels: force and cues against the training insertions per angle, cues against the
    calibration insertions per angle (deterministic bytes)."""
    from matplotlib.figure import Figure

    training, cal = needs["training"], needs["calibration"]
    target = float(needs["params"]["cue_target_pct"])
    steps = training["steps"]
    fig = Figure(figsize=(13, 3.8))
    force_ax, cue_ax, cal_ax = fig.subplots(1, 3)
    drawn = False
    for name in (m["name"] for m in training.get("force_models") or []):
        xs, ys = _series(
            steps, "per_angle", lambda s, n=name: ((s.get("force") or {}).get(n) or {}).get("mean_nrmse_pct")
        )
        if xs:
            force_ax.plot(
                xs, ys, "o-", color=FORCE_COLORS.get(name, "gray"), label=FORCE_NAMES.get(name, name)
            )
            drawn = True
    if drawn:
        force_ax.set_ylabel("mean NRMSE (%)")
        force_ax.legend(fontsize=8)
    else:
        _nothing(force_ax, "force not computed (see needs.json)")
    force_ax.set_title("Force, refitted on each subsample", fontsize=10)

    xs, ys = _series(steps, "per_angle", lambda s: (s.get("cues") or {}).get("balanced_within_s"))
    if xs:
        cue_ax.plot(xs, [100 * y for y in ys], "o-", color="black", label="balanced accuracy")
        xc, yc = _series(
            steps, "per_angle", lambda s: ((s.get("cues") or {}).get("seen") or {}).get("coverage_frames")
        )
        cue_ax.plot(xc, [100 * y for y in yc], "s:", color="gray", label="frames with a cue")
        cue_ax.axhline(target, color="tab:green", ls="--", lw=1, label=f"target {target:g} %")
        for s in steps:
            if "unavailable" in (s.get("cues") or {}):  # a step tried and not scored: at the axis, said
                where = cue_ax.get_xaxis_transform()
                cue_ax.text(s["per_angle"], 0.03, "not\nscored", transform=where, ha="center", fontsize=7)
        cue_ax.set_ylabel("%")
        cue_ax.legend(fontsize=8, loc="lower right")
    else:
        _nothing(cue_ax, "cues not scored (see needs.json)")
    cue_ax.set_title(f"Cues (within {float(needs['cue_within_s']):g} s), training units", fontsize=10)
    for ax in (force_ax, cue_ax):
        if ax.has_data():
            ax.set_xscale("log", base=2)
            ax.set_xticks(training["ladder"], [str(n) for n in training["ladder"]])
            ax.minorticks_off()
            ax.set_xlabel("training insertions per angle")
            ax.grid(alpha=0.3)

    loo = cal.get("leave_one_unit_out") or {}
    for i, entry in enumerate((loo.get("units") or {}).values()):
        xs, ys = _series(entry["steps"], "k", lambda s: s.get("balanced_within_s"))
        label = "each training unit left out" if i == 0 else "_nolegend_"
        cal_ax.plot(xs, [100 * y for y in ys], "-", color="silver", lw=1, label=label)
    xs, ys = _series(loo.get("mean") or [], "k", lambda s: s.get("balanced_within_s"))
    if xs:
        cal_ax.plot(xs, [100 * y for y in ys], "o-", color="black", label="mean, left out")
    for unit, entry in (cal.get("new_units") or {}).items():
        xs, ys = _series(entry["steps"], "k", lambda s: s.get("balanced_within_s"))
        cal_ax.plot(xs, [100 * y for y in ys], "D--", color="tab:purple", label=f"{unit} (new)")
    if cal_ax.has_data():
        cal_ax.axhline(target, color="tab:green", ls="--", lw=1)
        ks = [int(k) for k in cal["insertions_per_angle"]]
        cal_ax.set_xticks(ks, [str(k) for k in ks])
        cal_ax.set_xlabel("calibration insertions per angle")
        cal_ax.set_ylabel("balanced accuracy (%)")
        cal_ax.legend(fontsize=7, loc="best")
        cal_ax.grid(alpha=0.3)
    else:
        _nothing(cal_ax, "no calibration curve (see needs.json)")
    cal_ax.set_title("Cues of a new unit, calibrated", fontsize=10)
    fig.tight_layout()
    save_png(fig, path)
