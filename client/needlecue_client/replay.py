"""Replaying a recorded trial through the simulator's client, as if it were streamed live.

`replay` feeds one processed trial to `ForceClient.step` sample by sample and returns a table of the
predicted force beside the reference and the cue per sample; `cue_changes` is its cue timeline,
`rmse` its error per axis and `plot_replay` draws it. The axes are the model's `targets` (those its
reference sensor recorded): a model of fz alone gives fz, and fz_ref where the recording has it. This
is the `needlecue replay` command's module, not the simulator's: it needs pandas (and matplotlib for
the plot), imported inside the functions, and `needlecue_client` does not import it.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from needlecue_client.force import ForceClient, StreamMismatch
from needlecue_runtime.vocab import TRIAL_KEY, axes_of

if TYPE_CHECKING:
    import pandas as pd


def replay(frame: pd.DataFrame, client: ForceClient) -> pd.DataFrame:
    """Run one recorded trial through `client.step`, sample by sample as if live (after a reset).

    Returns one row per sample in t_s order: t_s, the predicted force of each of the model's
    `targets` (fx, fy, fz; or fz alone), the reference of each of them the frame has (fx_ref, ...),
    cue, angle_est_deg and reason (None without cues). No column for an axis the model does not give.
    """
    import pandas as pd

    missing = [c for c in (*client.channels, "t_s") if c not in frame.columns]
    if missing:
        raise StreamMismatch(
            f"the recording lacks column(s) {missing}: {client.name} reads {list(client.channels)} "
            f"and t_s; the recording has {list(frame.columns)}"
        )
    keys = [c for c in TRIAL_KEY if c in frame.columns]
    if keys and len(trials := frame[keys].drop_duplicates()) > 1:
        raise ValueError(f"replay takes one trial at a time, got {len(trials)} ({keys})")
    rows = frame.sort_values("t_s", kind="stable")
    volts = rows[list(client.channels)].to_numpy(np.float64)
    t = rows["t_s"].to_numpy(np.float64)
    force = np.empty((len(rows), len(client.targets)))
    cues: list[str | None] = []
    angles: list[float | None] = []
    reasons: list[str | None] = []
    client.reset()
    for i in range(len(rows)):
        out = client.step(volts[i], float(t[i]))
        force[i] = out.force_n
        cues.append(None if out.cue is None else out.cue.cue)
        angles.append(None if out.cue is None else out.cue.angle_est_deg)
        reasons.append(None if out.cue is None else out.cue.reason)
    result = pd.DataFrame({"t_s": t, **{c: force[:, i] for i, c in enumerate(client.targets)}})
    for c in client.targets:
        if c in rows.columns:
            result[f"{c}_ref"] = rows[c].to_numpy(np.float64)
    result["cue"] = pd.Series(cues, dtype=object)
    result["angle_est_deg"] = pd.Series(angles, dtype="float64")
    result["reason"] = pd.Series(reasons, dtype=object)
    return result


def cue_changes(replayed: pd.DataFrame) -> pd.DataFrame:
    """The rows of a `replay` result where the cue changes (the first row included): the timeline."""
    if replayed.empty or replayed["cue"].isna().all():
        return replayed.iloc[:0]
    cue = replayed["cue"].astype(object)
    return replayed[cue.ne(cue.shift())]


def rmse(replayed: pd.DataFrame) -> dict[str, float]:
    """RMSE in N per axis of a `replay` result against its reference (empty if it has none)."""
    return {
        c: float(np.sqrt(np.mean((replayed[c] - replayed[f"{c}_ref"]) ** 2)))
        for c in axes_of(replayed.columns)
        if f"{c}_ref" in replayed.columns
    }


CUE_COLOURS = {
    "wait": "#bbbbbb",
    "continue": "#7fc97f",
    "correct": "#fdb462",
    "stop": "#e7298a",
    "none": "#e0e0e0",  # no angle cue
}


def plot_replay(replayed: pd.DataFrame, out: Path, title: str) -> Path:
    """A PNG of predicted vs reference force over time, a panel per axis the model gives (fx, fy, fz;
    fz alone for a model of fz), the cue intervals shaded (Agg, no pyplot)."""
    from matplotlib.figure import Figure
    from matplotlib.patches import Patch

    names = axes_of(replayed.columns)  # the model's targets
    if not names:
        raise ValueError(f"no force column to plot (columns: {list(replayed.columns)})")
    fig = Figure(figsize=(10, 1 + 2 * len(names)), layout="constrained")
    axes = fig.subplots(len(names), 1, sharex=True, squeeze=False)[:, 0]
    t = replayed["t_s"].to_numpy()
    changes = cue_changes(replayed)
    starts = changes["t_s"].tolist()
    ends = [*starts[1:], float(t[-1])] if starts else []
    spans = list(zip(starts, ends, changes["cue"].tolist(), strict=True))
    for ax, c in zip(axes, names, strict=True):
        for lo, hi, cue in spans:
            ax.axvspan(lo, hi, color=CUE_COLOURS.get(cue, "#dddddd"), alpha=0.25, linewidth=0)
        if f"{c}_ref" in replayed.columns:
            ax.plot(t, replayed[f"{c}_ref"], color="black", linewidth=1.0, label="reference")
        ax.plot(t, replayed[c], color="tab:blue", linewidth=1.0, label="predicted")
        ax.set_ylabel(f"{c} (N)")
        ax.grid(alpha=0.3)
    handles, labels = axes[0].get_legend_handles_labels()
    seen = list(dict.fromkeys(cue for _, _, cue in spans))
    handles += [Patch(color=CUE_COLOURS.get(cue, "#dddddd"), alpha=0.4) for cue in seen]
    labels += [f"cue: {cue}" for cue in seen]
    axes[0].legend(handles, labels, loc="upper right", fontsize=8, ncols=2)
    axes[-1].set_xlabel("t (s)")
    fig.suptitle(title)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    return out
