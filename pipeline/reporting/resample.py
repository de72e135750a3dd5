"""The resample stage's reports in REPORT_DIR: ``offsets.csv`` (one row per trial), ``summary.md``
(counts, offset error against the simulator's truth, phase durations), ``offsets.png`` and
``trials.png`` (one aligned trial per angle, phases shaded).
"""

from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from needlecue_runtime.vocab import AXES, PHASES
from pipeline.config import ResampleParams
from pipeline.signals.resample import OFFSET_CSV_COLUMNS, Resampled


def write_offsets_csv(rows: list[dict[str, Any]], path: Path) -> None:
    """offsets.csv: one row per trial, in OFFSET_CSV_COLUMNS order."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=OFFSET_CSV_COLUMNS, lineterminator="\n")
        w.writeheader()
        w.writerows(rows)


def summary_markdown(rows: list[dict[str, Any]], durations: pd.DataFrame, p: ResampleParams) -> str:
    """Counts, offset error against the truth (when known) and phase durations."""
    ok = [r for r in rows if r["status"] == "ok"]
    aside = [r for r in rows if r["status"] != "ok"]
    lines = [
        "# Resample report",
        "",
        f"Grid {p.rate_hz:g} Hz; offset search ±{p.max_offset_s:g} s in {p.offset_step_s * 1e3:g} ms steps; "
        f"grid points in gaps > {p.max_gap_s:g} s dropped.",
        "",
        f"- trials: {len(rows)} ({len(ok)} ok, {len(aside)} set aside)"
        + (f"; {n_flagged} of the ok flagged" if (n_flagged := sum(1 for r in ok if r.get("flag"))) else ""),
        f"- batches: {len({r['batch_id'] for r in rows})}",
        f"- grid samples written: {sum(int(r['n_grid']) for r in ok)}; "
        f"dropped in gaps: {sum(int(r['n_dropped_gap']) for r in ok)}",
    ]
    if ok:
        q = np.array([float(r["quality"]) for r in ok])
        off = np.array([float(r["offset_s"]) for r in ok])
        lines.append(
            f"- estimated offsets: median {np.median(off) * 1e3:.1f} ms, range "
            f"[{off.min() * 1e3:.1f}, {off.max() * 1e3:.1f}] ms; quality (R²) median {np.median(q):.3f}, "
            f"min {q.min():.3f}"
        )
    err = np.array([float(r["error_s"]) for r in ok if r["error_s"] != ""])
    if err.size:
        a = np.abs(err) * 1e3
        period = 1e3 / p.rate_hz
        lines += [
            "",
            "## Offset error against the simulator's truth",
            "",
            "| trials | bias (ms) | median abs (ms) | p95 abs (ms) | max abs (ms) | within one grid period |",
            "|---|---|---|---|---|---|",
            f"| {err.size} | {err.mean() * 1e3:+.1f} | {np.median(a):.1f} | {np.percentile(a, 95):.1f} | "
            f"{a.max():.1f} | {np.mean(a <= period) * 100:.1f} % |",
        ]
    if len(durations):
        lines += [
            "",
            "## Phase durations (s per trial)",
            "",
            "| phase | median | min | max | trials with it |",
            "|---|---|---|---|---|",
        ]
        for ph in PHASES:
            col = durations[ph]
            lines.append(
                f"| {ph} | {col.median():.2f} | {col.min():.2f} | {col.max():.2f} | {int((col > 0).sum())} |"
            )
    flagged = [r for r in ok if r.get("flag")]
    if flagged:
        lines += [
            "",
            f"## Kept, flagged ({len(flagged)})",
            "",
            "Kept because nothing shows their files disagree; validation shows whether they hurt.",
            "",
        ]
        lines += [f"- {r['batch_id']} / {r['trial_id']}: {r['flag']}" for r in flagged]
    if aside:
        lines += ["", "## Set aside", ""]
        lines += [
            f"- {r['batch_id']} / {r['trial_id']}: {r['status'].removeprefix('set aside: ')}" for r in aside
        ]
    return "\n".join(lines) + "\n"


def plot_offsets(rows: list[dict[str, Any]], path: Path, period_s: float) -> None:
    """Offset error against the truth when it is known, else the estimates and their quality."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ok = [r for r in rows if r["status"] == "ok"]
    known = [r for r in ok if r["true_offset_s"] != ""]
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.2))
    if known:
        truth = np.array([float(r["true_offset_s"]) for r in known]) * 1e3
        err = np.array([float(r["error_s"]) for r in known]) * 1e3
        angle = np.array([float(r["angle_deg"]) for r in known])
        band = period_s * 1e3
        axes[0].axhspan(-band, band, color="0.92", label=f"± one grid period ({band:.0f} ms)")
        sc = axes[0].scatter(truth, err, c=angle, s=12, cmap="viridis")
        fig.colorbar(sc, ax=axes[0], label="angle (deg)")
        axes[0].axhline(0, color="0.5", lw=0.8)
        axes[0].set(xlabel="true offset (ms)", ylabel="estimate - truth (ms)", title="Offset error per trial")
        axes[0].legend(loc="upper left", fontsize=8)
        axes[1].hist(err, bins=40)
        axes[1].axvline(0, color="0.5", lw=0.8)
        axes[1].set(xlabel="estimate - truth (ms)", ylabel="trials", title="Offset error")
    else:
        est = np.array([float(r["offset_s"]) for r in ok]) * 1e3
        quality = np.array([float(r["quality"]) for r in ok])
        axes[0].hist(est, bins=40)
        axes[0].set(xlabel="estimated clock offset (ms)", ylabel="trials", title="Clock offset per trial")
        axes[1].hist(quality, bins=40, range=(0, 1))
        axes[1].set(xlabel="alignment quality (R² of force changes)", ylabel="trials", title="Fit quality")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100, metadata={"Software": None})
    plt.close(fig)


PHASE_COLOURS = {"insertion": "#d8ecd8", "dwell": "#fbeccb", "retraction": "#f6d5d5"}


def plot_example_trials(out_dir: Path, path: Path) -> None:
    """One aligned trial per angle: the channels (V) above the reference force (N), phases shaded."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    examples = []
    for file in sorted(out_dir.glob("*.parquet")):
        frame = pd.read_parquet(file)
        channels = json.loads(file.with_suffix(".json").read_text())["channels"]
        for angle, group in frame.groupby("angle_deg", sort=True):
            if angle not in [a for a, *_ in examples]:
                first = group[group.trial_id == group.trial_id.min()]
                examples.append((angle, first, channels))
    if not examples:
        return
    examples.sort(key=lambda e: e[0])
    fig, axes = plt.subplots(2, len(examples), figsize=(3.2 * len(examples), 5.5), sharex=True, squeeze=False)
    for col, (angle, trial, channels) in enumerate(examples):
        t = trial.t_s.to_numpy()
        for row in (0, 1):
            ax = axes[row, col]
            changes = np.flatnonzero(trial.phase.to_numpy()[1:] != trial.phase.to_numpy()[:-1]) + 1
            for start, stop in zip(np.r_[0, changes], np.r_[changes, len(t)], strict=True):
                colour = PHASE_COLOURS.get(trial.phase.iloc[start])
                if colour:
                    ax.axvspan(t[start], t[min(stop, len(t) - 1)], color=colour, lw=0)
        for c in channels:
            axes[0, col].plot(t, trial[c], lw=1, label=c)
        recorded = [a for a in AXES if a in trial.columns]  # the batch's reference.axes
        for axis in recorded:
            axes[1, col].plot(t, trial[axis], lw=1, label=axis)
        axes[0, col].set_title(f"{angle:g}° — {trial.batch_id.iloc[0]}/{trial.trial_id.iloc[0]}", fontsize=9)
        axes[1, col].set_xlabel("t (s)")
    axes[0, 0].set_ylabel("estimator (V)")
    axes[1, 0].set_ylabel("reference force (N)")
    axes[0, -1].legend(fontsize=7, loc="upper right")
    handles = [plt.Rectangle((0, 0), 1, 1, color=c) for c in PHASE_COLOURS.values()]
    axes[1, -1].legend([*axes[1, -1].get_lines(), *handles], [*recorded, *PHASE_COLOURS], fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=90, metadata={"Software": None})
    plt.close(fig)


def write_reports(result: Resampled, out_dir: Path, report_dir: Path, p: ResampleParams) -> None:
    """offsets.csv, summary.md, offsets.png and trials.png (from the tables in `out_dir`)."""
    report_dir.mkdir(parents=True, exist_ok=True)
    write_offsets_csv(result.rows, report_dir / "offsets.csv")
    (report_dir / "summary.md").write_text(summary_markdown(result.rows, result.durations, p))
    plot_offsets(result.rows, report_dir / "offsets.png", 1.0 / p.rate_hz)
    plot_example_trials(out_dir, report_dir / "trials.png")
