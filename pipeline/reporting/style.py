"""Shared look of the reports: colours (each model kind's from its table entry), number formats,
Markdown tables, PNGs without a version string (equal plots, equal bytes)."""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

from pipeline.modelling.kinds import TABLE

# the reference, then each model kind that names a colour (`ModelKind.color`); any other: matplotlib's next
COLORS = {"reference": "black", **{name: kind.color for name, kind in TABLE.items() if kind.color}}
PNG_METADATA: dict[str, Any] = {"Software": None}  # no version string: equal plots, equal bytes


def fmt(x: float | None, spec: str = ".4f") -> str:
    """A number in `spec`, or "" when unknown."""
    return "" if x is None or not math.isfinite(x) else format(x, spec)


def row(cells: Iterable[str]) -> str:
    return "| " + " | ".join(cells) + " |"


def table(header: Sequence[str], rows: Iterable[Sequence[str]]) -> list[str]:
    """A Markdown table's lines."""
    return [row(header), row("---" for _ in header), *(row(r) for r in rows)]


def save_png(fig: Any, path: Path, dpi: int = 100) -> None:
    """Save a matplotlib figure, creating its folder."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi, metadata=PNG_METADATA)


def placeholder_png(path: Path, message: str, figsize: tuple[float, float] = (6, 2)) -> None:
    """A figure that only says why there is nothing to plot."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=figsize)
    fig.text(0.5, 0.5, message, ha="center", va="center")
    save_png(fig, path)
