"""Typed views of `params.yaml`: one frozen, extra="forbid" model per section.

A typo in params.yaml (an unknown key, a wrong type) fails loudly here, when the
stage starts, instead of silently falling back to a default.
"""

from __future__ import annotations

from pathlib import Path
from typing import TypeVar

import yaml
from pydantic import BaseModel, ConfigDict, Field

DEFAULT_PARAMS = Path("params.yaml")


class Section(BaseModel):
    """Base of every params section: immutable, and unknown keys are errors."""

    model_config = ConfigDict(frozen=True, extra="forbid")


class DataParams(Section):
    """`data`: where a lab's own rig-log/1 batches live."""

    raw_dir: Path = Path("data/raw")


class EffectScales(Section):
    """`simulate.effects`: each physical effect of the rig simulator, 1 = as measured, 0 = off.

    Tests switch effects off one at a time to isolate them; nobody tunes them to flatter a
    model. Where each default comes from is documented in `pipeline/physics.py`.
    """

    tissue_inhomogeneity: float = Field(1.0, ge=0)
    batch_variation: float = Field(1.0, ge=0)
    gravity: float = Field(1.0, ge=0)
    part_variation: float = Field(1.0, ge=0)
    viscoelasticity: float = Field(1.0, ge=0)
    fsr_threshold: bool = True
    hysteresis: float = Field(1.0, ge=0)
    drift: float = Field(1.0, ge=0)
    repeatability: float = Field(1.0, ge=0)
    electrical_noise: float = Field(1.0, ge=0)
    adc: bool = True
    clock_jitter: float = Field(1.0, ge=0)
    dropped_samples: float = Field(1.0, ge=0)
    clock_offset: float = Field(1.0, ge=0)
    reference_noise: float = Field(1.0, ge=0)


class SimulateParams(Section):
    """`simulate`: the built-in rig simulator that stands in for a lab."""

    enabled: bool = True
    seed: int = 20240115
    angles_deg: tuple[float, ...] = (0, 15, 30, 45, 60, 75)
    train_batches: int = Field(3, ge=0)
    trials_per_angle: int = Field(7, ge=0, description="per angle in each training batch")
    heldout_trials_per_angle: int = Field(21, ge=0, description="in the held-out batch of each angle")
    fsr_rate_hz: float = Field(30.0, gt=0)
    ref_rate_hz: float = Field(100.0, gt=0)
    unit_id: str = "est-sim-001"
    effects: EffectScales = EffectScales()


class IngestParams(Section):
    """`ingest`: what counts as a plausible stream."""

    min_rate_hz: float = Field(5.0, gt=0)
    max_rate_hz: float = Field(10_000.0, gt=0)
    min_samples: int = Field(10, ge=2)


class ResampleParams(Section):
    """`resample`: clock alignment and the common grid."""

    rate_hz: float = Field(30.0, gt=0)
    max_offset_s: float = Field(0.5, gt=0, description="search window for the clock offset, +/-")
    offset_step_s: float = Field(0.002, gt=0)
    max_gap_s: float = Field(0.25, gt=0, description="grid points inside longer gaps are dropped")
    lowpass_order: int = Field(4, ge=1)


class SplitParams(Section):
    """`split`: per-angle train/val/test by trial; held-out batches form the external set."""

    seed: int = 0
    val_fraction: float = Field(0.05, ge=0, lt=1)
    test_fraction: float = Field(0.10, ge=0, lt=1)
    external_batches: tuple[str, ...] = ("*heldout*",)


S = TypeVar("S", bound=Section)


def load_section(model: type[S], section: str, path: Path = DEFAULT_PARAMS) -> S:
    """Read one section of params.yaml into its model (missing section = all defaults)."""
    with Path(path).open() as f:
        params = yaml.safe_load(f) or {}
    return model.model_validate(params.get(section) or {})
