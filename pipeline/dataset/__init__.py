"""The processed dataset: its table schema and the per-angle train/val/test/external split."""
