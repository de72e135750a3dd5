"""The evaluation's figures (matplotlib's object API on the Agg canvas: no pyplot state) and the
data of DVC's plots: Figs. 7-8 of the paper, the angle-gap heatmap, `plots/{gap,profile}.csv`."""

from __future__ import annotations

import csv
from collections.abc import Callable, Iterable, Mapping, Sequence
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd

from needlecue_runtime.vocab import TRIAL_KEY, axes_of, sorted_angles
from pipeline.metrics.document import Evaluation, GapPoint
from pipeline.metrics.evaluation import EvalSet, Scored
from pipeline.metrics.paper import reference_angle
from pipeline.metrics.scores import GAP_TOL, gap_of, mean_over_axes
from pipeline.modelling.kinds import kind_label
from pipeline.reporting.style import COLORS, fmt, placeholder_png, save_png

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

FIGURES = ("fig7_profiles.png", "fig8_gaps.png", "gap_matrix.png")


def gap_rows(metrics: Evaluation, kinds: Sequence[str]) -> list[dict[str, str]]:
    """plots/gap.csv: one row per gap present, mean NRMSE over axes and pairs per model."""
    curve = metrics.gap_curve
    gaps = sorted({float(g) for m in curve.values() for g in m})
    return [
        {"gap_deg": f"{g:g}", **{m: fmt(_gap_mean(curve.get(m, {}), f"{g:g}")) for m in kinds}} for g in gaps
    ]


def _gap_mean(points: Mapping[str, GapPoint], gap: str) -> float | None:
    point = points.get(gap)
    return None if point is None else point.mean


def first_trial(frame: pd.DataFrame) -> np.ndarray:
    """Row positions of the first trial by (batch_id, trial_id), in time order: a fixed,
    unselected trial rather than a flattering one."""
    keys = frame[list(TRIAL_KEY)].astype(str)
    b0, t0 = min(zip(keys["batch_id"], keys["trial_id"], strict=True))
    rows = np.flatnonzero((keys["batch_id"].to_numpy() == b0) & (keys["trial_id"].to_numpy() == t0))
    return rows[np.argsort(frame["t_s"].to_numpy()[rows], kind="stable")]


def profile_rows(
    eval_sets: Mapping[str, EvalSet], preds: Scored, kinds: Sequence[str]
) -> list[dict[str, str]]:
    """plots/profile.csv: Fz (or, where the reference did not record it, its first axis) of one
    held-out trial at the reference angle, reference and each model."""
    angle = reference_angle(list(eval_sets))
    if angle is None:
        return []
    es = eval_sets[angle]
    rows = first_trial(es.frame)
    axis = "fz" if "fz" in es.axes else es.axes[0]
    k = es.axes.index(axis)
    cols = {m: _column(preds, m, angle, angle, axis) for m in kinds}
    return [
        {
            "t_s": fmt(float(es.frame["t_s"].iloc[i]), ".6g"),
            "reference": fmt(float(es.ref[i, k]), ".6g"),
            **{m: "" if p is None else fmt(float(p[i]), ".6g") for m, p in cols.items()},
        }
        for i in rows
    ]


def _column(preds: Scored, model: str, train_angle: str, data_angle: str, axis: str) -> np.ndarray | None:
    """One force axis of a model's predictions on an angle's scored set (None: not predicted, or an
    axis the model does not estimate)."""
    p = preds.on_eval.get((model, train_angle, data_angle))
    axes = preds.axes_of(model, train_angle)
    return None if p is None or axis not in axes else p[:, axes.index(axis)]


def write_csv(path: Path, rows: list[dict[str, str]], columns: Sequence[str]) -> None:
    """CSV with a fixed column order and Unix line ends."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(columns), lineterminator="\n")
        w.writeheader()
        w.writerows(rows)


def _finish_profiles(fig: Figure, grid: np.ndarray, path: Path) -> None:
    """Time axis labels on the bottom row, one legend above the grid, then save."""
    for ax in grid[-1]:
        ax.set_xlabel("t (s)")
    handles, labels = grid[0][0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside upper center", ncols=len(labels))
    save_png(fig, path)


def _profile_panels(
    axes_row: Sequence[Axes],
    shown: Sequence[str],
    es: EvalSet,
    lines: Mapping[str, Callable[[str], np.ndarray | None]],
    rows: np.ndarray,
) -> None:
    """One panel per force axis `shown`: the reference and each model's line (`lines`: model ->
    its column of an axis, None where it has none); a panel whose axis the trial did not record
    says so."""
    t = es.frame["t_s"].to_numpy()[rows]
    for axis, ax in zip(shown, axes_row, strict=True):
        ax.grid(alpha=0.3)
        if axis not in es.axes:
            ax.text(0.5, 0.5, "not recorded", ha="center", va="center", transform=ax.transAxes)
            continue
        ax.plot(t, es.ref[rows, es.axes.index(axis)], color=COLORS["reference"], lw=1.6, label="reference")
        for model, column in lines.items():
            if (p := column(axis)) is not None:
                ax.plot(t, p[rows], color=COLORS.get(model), lw=1.0, alpha=0.85, label=kind_label(model))


def plot_profiles(eval_sets: Mapping[str, EvalSet], preds: Scored, kinds: Sequence[str], path: Path) -> None:
    """Fig. 7: reference against each model on one external trial per angle (rows) and axis (cols)."""
    from matplotlib.figure import Figure

    angles = [a for a in eval_sets if any((m, a, a) in preds.on_eval for m in kinds)]
    if not angles:
        placeholder_png(path, "no trained model to plot")
        return
    shown = axes_of({a for angle in angles for a in eval_sets[angle].axes})
    fig = Figure(figsize=(4 * len(shown), 2.3 * len(angles) + 0.8), layout="constrained")
    grid = fig.subplots(len(angles), len(shown), squeeze=False, sharex="row")
    for r, angle in enumerate(angles):
        es = eval_sets[angle]
        rows = first_trial(es.frame)
        lines = {
            m: partial(_column, preds, m, angle, angle) for m in kinds if (m, angle, angle) in preds.on_eval
        }
        _profile_panels(grid[r], shown, es, lines, rows)
        trial = es.frame["trial_id"].iloc[rows[0]]
        for axis, ax in zip(shown, grid[r], strict=True):
            ax.set_title(f"{angle}° models, {es.source} trial {trial}: F{axis[1]}", fontsize=9)
        grid[r][0].set_ylabel("force (N)")
    _finish_profiles(fig, grid, path)


def gap_examples(
    train_angles: Iterable[str], data_angles: Iterable[str], gaps: Sequence[float], preferred: str = "15"
) -> list[tuple[str, str]]:
    """(train angle, data angle) per gap for Fig. 8: the 15° model on 15+gap (else 15−gap), like
    the paper; without such a pair, the first train angle that has one."""
    trains, datas = sorted_angles(train_angles), sorted_angles(data_angles)
    starts = ([preferred] if preferred in trains else []) + [a for a in trains if a != preferred]
    out = []
    for gap in gaps:
        for start in starts:
            hits = [d for d in datas if abs(gap_of(start, d) - gap) <= GAP_TOL]
            if hits:
                above = [d for d in hits if float(d) > float(start)]
                out.append((start, (above or hits)[0]))
                break
    return out


def plot_gaps(
    eval_sets: Mapping[str, EvalSet],
    preds: Scored,
    kinds: Sequence[str],
    gaps: Sequence[float],
    path: Path,
) -> None:
    """Fig. 8: one angle's models on trials of other angles, one row per gap."""
    from matplotlib.figure import Figure

    trained = {t for (_, t, _) in preds.on_eval}
    examples = [
        (t, d)
        for t, d in gap_examples(trained, eval_sets, gaps)
        if any((m, t, d) in preds.on_eval for m in kinds)
    ]
    if not examples:
        placeholder_png(path, "no (model, data) pair with the configured angle gaps")
        return
    shown = axes_of({a for _, d in examples for a in eval_sets[d].axes})
    fig = Figure(figsize=(4 * len(shown), 2.6 * len(examples) + 0.8), layout="constrained")
    grid = fig.subplots(len(examples), len(shown), squeeze=False)
    for r, (train_angle, data_angle) in enumerate(examples):
        es = eval_sets[data_angle]
        rows = first_trial(es.frame)
        lines = {
            m: partial(_column, preds, m, train_angle, data_angle)
            for m in kinds
            if (m, train_angle, data_angle) in preds.on_eval
        }
        _profile_panels(grid[r], shown, es, lines, rows)
        gap = gap_of(train_angle, data_angle)
        for axis, ax in zip(shown, grid[r], strict=True):
            ax.set_title(
                f"{train_angle}° models on a {data_angle}° trial ({gap:g}° gap): F{axis[1]}", fontsize=9
            )
        grid[r][0].set_ylabel("force (N)")
    _finish_profiles(fig, grid, path)


def plot_gap_matrix(metrics: Evaluation, kinds: Sequence[str], path: Path) -> None:
    """Heatmaps of mean NRMSE over axes, train angle (rows) against data angle (cols), per model."""
    from matplotlib.figure import Figure

    matrix = metrics.angle_gap_matrix
    shown = [m for m in kinds if m in matrix]
    if not shown:
        placeholder_png(path, "no trained model to plot")
        return
    angles = sorted_angles(
        [a for m in shown for a in matrix[m]] + [d for m in shown for row in matrix[m].values() for d in row]
    )
    values = {
        m: np.array(
            [
                [
                    np.nan if (v := mean_over_axes(matrix[m].get(t, {}).get(d, {}))) is None else v
                    for d in angles
                ]
                for t in angles
            ]
        )
        for m in shown
    }
    finite = np.concatenate([v[np.isfinite(v)] for v in values.values()])
    vmax = float(finite.max()) if finite.size else 1.0
    fig = Figure(figsize=(4.4 * len(shown) + 0.8, 4.4), layout="constrained")
    panels = fig.subplots(1, len(shown), squeeze=False)[0]
    image = None
    for ax, m in zip(panels, shown, strict=True):
        v = values[m]
        image = ax.imshow(np.ma.masked_invalid(v), cmap="viridis", vmin=0.0, vmax=vmax)
        for i in range(len(angles)):
            for j in range(len(angles)):
                if np.isfinite(v[i, j]):
                    dark = v[i, j] < 0.6 * vmax
                    ax.text(
                        j,
                        i,
                        f"{v[i, j]:.1f}",
                        ha="center",
                        va="center",
                        fontsize=8,
                        color="white" if dark else "black",
                    )
        ax.set_xticks(range(len(angles)), [f"{a}°" for a in angles])
        ax.set_yticks(range(len(angles)), [f"{a}°" for a in angles])
        ax.set_xlabel("data angle")
        ax.set_ylabel("train angle (model)")
        ax.set_title(f"{kind_label(m)}: mean NRMSE over axes (%)", fontsize=10)
    if image is not None:
        fig.colorbar(image, ax=list(panels), shrink=0.8, label="NRMSE (%)")
    save_png(fig, path)
