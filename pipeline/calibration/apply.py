"""Which units' calibrations apply to which trained model: a calibration applies to the models it
was made with (their checkpoint hashes), never to a retrained one."""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

from needlecue_runtime.unit_calibration import read_units, transform_for
from needlecue_runtime.vocab import angle_name
from pipeline.modelling.checkpoint import CHECKPOINT_FILE, checkpoint_sha256, load_checkpoint
from pipeline.modelling.split_predictions import UnitTransforms


def unit_transforms(
    cal_dir: Path, models_dir: Path, kinds: Iterable[str], angles: Iterable[float]
) -> dict[tuple[str, str], UnitTransforms]:
    """Per (kind, angle) model, the units whose calibration was made with that very model."""
    units = read_units(cal_dir)
    out: dict[tuple[str, str], UnitTransforms] = {}
    for kind in kinds:
        for angle in (angle_name(a) for a in angles):
            path = models_dir / kind / angle / CHECKPOINT_FILE
            if not units or not path.is_file():
                continue
            sha = checkpoint_sha256(load_checkpoint(path))
            found = {u: t for u, d in units.items() if (t := transform_for(d, kind, angle, sha)) is not None}
            if found:
                out[kind, angle] = found
    return out
