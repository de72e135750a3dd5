"""Reading the calibration rows the split stage set apart (`DATA_DIR/calibration/<angle>.parquet`),
grouped by estimator unit."""

from __future__ import annotations

from pathlib import Path

import pandas as pd

from needlecue_runtime.vocab import CALIBRATION


def calibration_rows(data_dir: Path) -> dict[str, pd.DataFrame]:
    """{unit_id: its calibration rows over every angle}, units in sorted order; {} without any."""
    data_dir = Path(data_dir)
    if not data_dir.is_dir():
        raise FileNotFoundError(f"{data_dir}: no such folder (run the split stage first)")
    files = sorted((data_dir / CALIBRATION).glob("*.parquet"))
    frames = [pd.read_parquet(f) for f in files]
    frames = [f for f in frames if not f.empty]
    if not frames:
        return {}
    rows = pd.concat(frames, ignore_index=True)
    if "unit_id" not in rows.columns:
        raise ValueError(f"{data_dir / CALIBRATION}: calibration rows without a unit_id column")
    return {str(u): f.reset_index(drop=True) for u, f in rows.groupby("unit_id", sort=True)}
