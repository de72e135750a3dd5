"""A processed angle folder and a small params file, as the split stage and params.yaml give them."""

from __future__ import annotations

from pathlib import Path

from tests.modelling.frames import make_frame

PARAMS = """\
ls:
  fit_intercept: false
fnn:
  hidden: [6]
  max_epochs: 4
  patience: 2
  batch_size: 32
lstm:
  window: 4
  hidden: 5
  max_epochs: 3
  patience: 2
  batch_size: 32
"""


def write_split(data_dir: Path, train_seed: int = 0, val_rows: bool = True, test_seed: int = 2) -> Path:
    """A processed angle folder as the split stage writes it."""
    data_dir.mkdir(parents=True, exist_ok=True)
    val = make_frame(1, seed=1, batch_id="b2")
    make_frame(3, seed=train_seed).to_parquet(data_dir / "train.parquet", index=False)
    (val if val_rows else val.iloc[:0]).to_parquet(data_dir / "val.parquet", index=False)
    make_frame(1, seed=test_seed, batch_id="b3").to_parquet(data_dir / "test.parquet", index=False)
    make_frame(2, seed=3, batch_id="heldout").to_parquet(data_dir / "external.parquet", index=False)
    return data_dir
