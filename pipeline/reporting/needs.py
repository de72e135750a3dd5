"""How much data a lab needs, in the report: the `## How much data you need` section and its figure,
rendered from the needs stage's needs.json (`pipeline.needs.document.Needs`)."""

from __future__ import annotations

import textwrap
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, TypeVar

from pipeline.modelling.kinds import kind_label
from pipeline.needs.document import (
    CueFigures,
    CueScores,
    CueUnscored,
    MeanScores,
    Needs,
    ScoresAt,
    Step,
    UnscoredAt,
    force_kind,
)
from pipeline.reporting.style import COLORS, fmt, save_png, table

S = TypeVar("S")  # a point of a curve: a ladder step, a calibration step


def force_name(name: str) -> str:
    """A force curve's name in the table and the legend: its kind, or the networks' stand-in."""
    kind, stand_in = force_kind(name)
    return "networks' stand-in" if stand_in else kind_label(kind)


def force_color(name: str) -> str:
    """A force curve in its kind's colour."""
    return COLORS.get(force_kind(name)[0], "gray")


def _pct(x: float | None) -> str:
    return "–" if x is None else f"{100 * x:.1f} %"


def _cue_cells(figures: CueFigures | MeanScores | Any | None) -> list[str]:
    """Balanced within the cue time, and what the trainee sees: wrong at the end, wrong frames, frames
    with a cue; or why there is nothing."""
    if isinstance(figures, CueUnscored):
        return [f"not scored: {figures.unavailable}", "", "", ""]
    if not isinstance(figures, CueScores | MeanScores):
        return ["–"] * 4
    seen = figures.seen
    return [
        _pct(figures.balanced_within_s),
        _pct(seen.wrong_final),
        _pct(seen.wrong_frames),
        _pct(seen.coverage_frames),
    ]


def _balanced(figures: object) -> float | None:
    return figures.balanced_within_s if isinstance(figures, CueScores | MeanScores) else None


def _coverage(figures: object) -> float | None:
    return figures.seen.coverage_frames if isinstance(figures, CueScores) else None


def _force(step: Step, name: str) -> float | None:
    f = step.force.get(name)
    return None if f is None else f.mean_nrmse_pct


def _cue_header(within_s: float) -> list[str]:
    return [f"cues: balanced within {within_s:g} s", "wrong at the end", "wrong frames", "frames with a cue"]


def training_table(needs: Needs) -> list[str]:
    """One row per step of the ladder: its trials, each force model's mean NRMSE, the cues."""
    training = needs.training
    models = [m.name for m in training.force_models]
    header = [
        "insertions per angle",
        "trials (per unit)",
        *(f"{force_name(m)}: NRMSE %" for m in models),
        *_cue_header(float(needs.cue_within_s)),
    ]
    rows = []
    for s in training.steps:
        units = ", ".join(str(n) for n in s.by_unit.values())
        force = [fmt(_force(s, m), ".2f") or "–" for m in models]
        rows.append([str(s.per_angle), f"{s.trials} ({units})", *force, *_cue_cells(s.cues)])
    return table(header, rows)


def _trials(step: ScoresAt | UnscoredAt) -> str:
    return str(step.trials) if isinstance(step, ScoresAt) else ""


def calibration_table(needs: Needs) -> list[str]:
    """One row per unit and k: each training unit left out, their mean, each new unit."""
    cal = needs.calibration
    rows = []
    loo = cal.leave_one_unit_out
    for unit, entry in (loo.units if loo else {}).items():
        for s in entry.steps:
            rows.append([f"{unit} (left out)", str(s.k), str(entry.test_trials), *_cue_cells(s)])
    for m in loo.mean if loo else []:
        rows.append([f"**mean of {m.units} left out**", str(m.k), "", *_cue_cells(m)])
    for unit, new in cal.new_units.items():
        for s in new.steps:
            rows.append([f"{unit} (new unit)", str(s.k), _trials(s), *_cue_cells(s)])
    if not rows:
        return []
    header = [
        "unit",
        "calibration insertions per angle",
        "trials scored",
        *_cue_header(float(needs.cue_within_s)),
    ]
    return table(header, rows)


def how_much_data_you_need(needs: Needs, figure: str = "needs/needs.png") -> str:
    """The `## How much data you need` section (the figure's link relative to `reports/`)."""
    training, cal = needs.training, needs.calibration
    have = training.have_per_angle
    models = "; ".join(m.about for m in training.force_models)
    per_angle = ", ".join(f"{a}°: {n}" for a, n in have.items())
    lines = [
        "## How much data you need",
        "",
        "From this lab's own data, subsampled (the `needs` stage): force and angle-cue figures against the "
        "training insertions per angle, and the cues against a new unit's calibration insertions per angle. "
        f"Training insertions per angle here: {per_angle}. The subsamples take, {training.subsample}. "
        f"The force figures are those of models refitted on each subsample ({models or 'none built'}), "
        f"not of the trained LSTM, scored on {training.force_scored_on}. The cues: "
        f"{training.cues_scored_on}. Force against calibration insertions is {cal.force}.",
        "",
        "**What to record next**",
        "",
        *(f"- {s}" for s in needs.advice or ["(no advice: nothing could be computed)"]),
        "",
        "### Training insertions per angle",
        "",
        *training_table(needs),
        "",
    ]
    cal_rows = calibration_table(needs)
    if cal_rows:
        lines += ["### Calibration insertions per angle", "", *cal_rows, ""]
    if needs.not_computed:
        lines += ["Not computed, and why:", ""]
        lines += [f"- {n.what}: {n.why}" for n in needs.not_computed]
        lines.append("")
    lines += [f"![Force and cue figures against the insertions per angle]({figure})", ""]
    return "\n".join(lines)


def _series(
    steps: Sequence[S], x: Callable[[S], int], get: Callable[[S], float | None]
) -> tuple[list[int], list[float]]:
    """(xs, figures) of the steps that have the figure."""
    xs, ys = [], []
    for s in steps:
        v = get(s)
        if v is not None:
            xs.append(int(x(s)))
            ys.append(float(v))
    return xs, ys


def _nothing(ax: Any, why: str) -> None:
    ax.text(0.5, 0.5, textwrap.fill(why, 40), ha="center", va="center", fontsize=8, transform=ax.transAxes)
    ax.set_xticks([])
    ax.set_yticks([])


def _per_angle(s: Step) -> int:
    return s.per_angle


def _k(s: ScoresAt | UnscoredAt | MeanScores | Any) -> int:
    return int(s.k)


def plot_needs(needs: Needs, path: Path) -> None:
    """Three panels: force and cues against the training insertions per angle, cues against the
    calibration insertions per angle (deterministic bytes)."""
    from matplotlib.figure import Figure

    training, cal = needs.training, needs.calibration
    target = float(needs.params.cue_target_pct)
    steps = training.steps
    fig = Figure(figsize=(13, 3.8))
    force_ax, cue_ax, cal_ax = fig.subplots(1, 3)
    drawn = False
    for name in (m.name for m in training.force_models):
        xs, ys = _series(steps, _per_angle, lambda s, n=name: _force(s, n))
        if xs:
            force_ax.plot(xs, ys, "o-", color=force_color(name), label=force_name(name))
            drawn = True
    if drawn:
        force_ax.set_ylabel("mean NRMSE (%)")
        force_ax.legend(fontsize=8)
    else:
        _nothing(force_ax, "force not computed (see needs.json)")
    force_ax.set_title("Force, refitted on each subsample", fontsize=10)

    xs, ys = _series(steps, _per_angle, lambda s: _balanced(s.cues))
    if xs:
        cue_ax.plot(xs, [100 * y for y in ys], "o-", color="black", label="balanced accuracy")
        xc, yc = _series(steps, _per_angle, lambda s: _coverage(s.cues))
        cue_ax.plot(xc, [100 * y for y in yc], "s:", color="gray", label="frames with a cue")
        cue_ax.axhline(target, color="tab:green", ls="--", lw=1, label=f"target {target:g} %")
        for s in steps:
            if isinstance(s.cues, CueUnscored):  # a step tried and not scored: at the axis, said
                where = cue_ax.get_xaxis_transform()
                cue_ax.text(s.per_angle, 0.03, "not\nscored", transform=where, ha="center", fontsize=7)
        cue_ax.set_ylabel("%")
        cue_ax.legend(fontsize=8, loc="lower right")
    else:
        _nothing(cue_ax, "cues not scored (see needs.json)")
    cue_ax.set_title(f"Cues (within {float(needs.cue_within_s):g} s), training units", fontsize=10)
    for ax in (force_ax, cue_ax):
        if ax.has_data():
            ax.set_xscale("log", base=2)
            ax.set_xticks(training.ladder, [str(n) for n in training.ladder])
            ax.minorticks_off()
            ax.set_xlabel("training insertions per angle")
            ax.grid(alpha=0.3)

    loo = cal.leave_one_unit_out
    for i, entry in enumerate((loo.units if loo else {}).values()):
        xs, ys = _series(entry.steps, _k, _balanced)
        label = "each training unit left out" if i == 0 else "_nolegend_"
        cal_ax.plot(xs, [100 * y for y in ys], "-", color="silver", lw=1, label=label)
    xs, ys = _series(loo.mean if loo else [], _k, _balanced)
    if xs:
        cal_ax.plot(xs, [100 * y for y in ys], "o-", color="black", label="mean, left out")
    for unit, new in cal.new_units.items():
        xs, ys = _series(new.steps, _k, _balanced)
        cal_ax.plot(xs, [100 * y for y in ys], "D--", color="tab:purple", label=f"{unit} (new)")
    if cal_ax.has_data():
        cal_ax.axhline(target, color="tab:green", ls="--", lw=1)
        ks = [int(k) for k in cal.insertions_per_angle]
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
