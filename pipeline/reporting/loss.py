"""The loss curve of one trained model (train and validation loss per epoch), logged with its run."""

from __future__ import annotations

from pathlib import Path

import pandas as pd

from pipeline.reporting.style import save_png


def loss_curve_png(history_csv: Path, title: str, path: Path) -> bool:
    """A PNG of `history.csv`'s loss curves (log scale); False when there is no history."""
    if not history_csv.is_file():
        return False
    from matplotlib.figure import Figure

    h = pd.read_csv(history_csv)
    fig = Figure(figsize=(5, 3.2))
    ax = fig.subplots()
    ax.plot(h["epoch"], h["train_loss"], label="train")
    if h["val_loss"].notna().any():
        ax.plot(h["epoch"], h["val_loss"], label="validation")
    ax.set(xlabel="epoch", ylabel="scaled MSE", yscale="log", title=title)
    ax.legend()
    fig.tight_layout()
    save_png(fig, path, dpi=90)
    return True
