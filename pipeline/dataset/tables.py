"""The resampled and processed table: its column order and Arrow schema (ids, channels, forces),
and Parquet written so that equal data give equal bytes. The resample stage writes it per batch,
the split stage per angle and split.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq

from needlecue_runtime.vocab import AXES, ID_COLUMNS

TEXT_IDS = frozenset(
    {"batch_id", "unit_id", "trial_id", "tissue_point", "phase"}
)  # the other columns are float64


def columns_for(channels: Iterable[str], axes: Iterable[str] = AXES) -> list[str]:
    """Column order of a table with these estimator channels and recorded force axes: ids, channels,
    forces."""
    return [*ID_COLUMNS, *channels, *axes]


def table_schema(channels: Iterable[str], axes: Iterable[str] = AXES) -> pa.Schema:
    """Arrow schema of a table with these estimator channels and recorded force axes."""
    ids = [pa.field(c, pa.string() if c in TEXT_IDS else pa.float64()) for c in ID_COLUMNS]
    return pa.schema([*ids, *(pa.field(c, pa.float64()) for c in [*channels, *axes])])


def write_table(table: pa.Table, path: Path) -> None:
    """Parquet with fixed settings and no pandas metadata, so equal data give equal bytes."""
    path.parent.mkdir(parents=True, exist_ok=True)
    pq.write_table(table.replace_schema_metadata(None), path, compression="zstd")
