"""The angle cues' figures in the report: the confusion matrices and the time-to-cue curves, drawn from
the cues stage's evaluation (`pipeline.cues.document`), or a placeholder saying why there is none."""

from __future__ import annotations

import textwrap
from pathlib import Path

import numpy as np

from needlecue_runtime.cues.pack import CUES, DEVIATION_GROUPS, METHODS, VERDICTS
from pipeline.cues.document import CueEvaluation, SkippedCues
from pipeline.reporting.style import save_png


def method_label(method: str) -> str:
    return {"combined": "angle estimate + force check (ours)", "paper": "profile comparison (paper)"}[method]


def _no_results(evaluation: CueEvaluation) -> str | None:
    """Why there is nothing to plot (None if there is)."""
    if isinstance(evaluation, SkippedCues):
        return f"Cue evaluation skipped: {evaluation.skipped}"
    if not scored_kinds(evaluation):
        return "No model's cues were scored"
    return None


def scored_kinds(evaluation: CueEvaluation) -> list[str]:
    """The model kinds with results, in the evaluation's order."""
    return [k for k in evaluation.kinds if k in evaluation.results]


def _placeholder(message: str, path: Path) -> None:
    """A small figure that only says why there is no plot (deterministic bytes)."""

    from matplotlib.figure import Figure

    fig = Figure(figsize=(6, 2))
    fig.text(0.5, 0.5, textwrap.fill(message, 70), ha="center", va="center", fontsize=9, wrap=True)
    save_png(fig, path)


def plot_confusion(evaluation: CueEvaluation, path: Path) -> None:
    from matplotlib.figure import Figure

    if (why := _no_results(evaluation)) is not None:
        _placeholder(why, path)
        return
    res, kinds = evaluation.results, scored_kinds(evaluation)
    methods = [m for m in METHODS if any(m in res[k] for k in kinds)]
    rows = max(len(kinds), 1)
    fig = Figure(figsize=(5 * len(methods), 3.2 * rows))
    axes = fig.subplots(rows, len(methods), squeeze=False)
    for r, kind in enumerate(kinds):
        for c, method in enumerate(methods):
            if method not in res[kind]:
                axes[r][c].set_axis_off()
                continue
            ax = axes[r][c]
            m = np.asarray(res[kind][method].confusion_final.counts)
            share = m / np.maximum(m.sum(axis=1, keepdims=True), 1)
            ax.imshow(share, cmap="Blues", vmin=0, vmax=1, aspect="auto")
            for i in range(m.shape[0]):
                for j in range(m.shape[1]):
                    ax.text(
                        j,
                        i,
                        str(m[i, j]),
                        ha="center",
                        va="center",
                        color="white" if share[i, j] > 0.6 else "black",
                        fontsize=10,
                    )
            ax.set_xticks(range(len(CUES)), CUES)
            ax.set_yticks(range(len(VERDICTS)), VERDICTS)
            acc = res[kind][method].accuracy_final
            ax.set_title(
                f"{kind.upper()}: {method_label(method)}\naccuracy {100 * (acc or 0):.1f} %", fontsize=9
            )
            ax.set_xlabel("cue at the end of the insertion")
            ax.set_ylabel("true cue")
    fig.tight_layout()
    save_png(fig, path)


def plot_time_to_cue(evaluation: CueEvaluation, path: Path) -> None:
    """ECDF of the seconds into the insertion until the cue is right (and stays right)."""
    from matplotlib.figure import Figure

    if (why := _no_results(evaluation)) is not None:
        _placeholder(why, path)
        return
    res, kinds = evaluation.results, scored_kinds(evaluation)
    cols = max(len(kinds), 1)
    fig = Figure(figsize=(4.2 * cols, 3.6))
    axes = fig.subplots(1, cols, squeeze=False)[0]
    colors = {"0": "tab:green", "15": "tab:orange", "30": "tab:red", ">=45": "tab:purple"}
    for ax, kind in zip(axes, kinds, strict=False):
        for method, style in (("combined", "-"), ("paper", "--")):
            if method not in res[kind]:
                continue
            for g in DEVIATION_GROUPS:
                d = res[kind][method].time_to_cue[g]
                if not d.trials:
                    continue
                right = np.asarray(d.seconds, dtype=float)
                x = np.concatenate([[0.0], right, [12.0]])
                y = np.concatenate([[0.0], np.arange(1, len(right) + 1), [len(right)]]) / d.trials
                ax.step(
                    x,
                    y,
                    where="post",
                    color=colors[g],
                    ls=style,
                    lw=1.3,
                    label=f"{g}° {'ours' if method == 'combined' else 'paper'}",
                )
        ax.set_xlim(0, 12)
        ax.set_ylim(0, 1.02)
        ax.set_title(kind.upper(), fontsize=10)
        ax.set_xlabel("seconds into the insertion")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("share of trials with the right cue to the end")
    axes[-1].legend(fontsize=7, loc="lower right", ncol=2)
    fig.tight_layout()
    save_png(fig, path)
