"""Typed views of `params.yaml`: one frozen, extra="forbid" model per section.

A typo in params.yaml (an unknown key, a wrong type) fails loudly here, when the
stage starts, instead of silently falling back to a default. A model kind's own section
(`ls`, ...) is a `Section` defined in its module, `pipeline.modelling.kinds.<name>`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal, TypeVar

import yaml
from pydantic import Field, field_validator, model_validator

from needlecue_runtime.params import AUTO_EVIDENCE_LEVELS as AUTO_EVIDENCE_LEVELS
from needlecue_runtime.params import CuesParams as CuesParams
from needlecue_runtime.params import InputParams as InputParams
from needlecue_runtime.params import KindName as KindName
from needlecue_runtime.params import Section
from needlecue_runtime.vocab import AXES, KINDS

DEFAULT_PARAMS = Path("params.yaml")


class DataParams(Section):
    """`data`: where a lab's own rig-log/1 batches live."""

    raw_dir: Path = Path("data/raw")


class EffectScales(Section):
    """`simulate.effects`: each physical effect of the rig simulator, 1 = as measured, 0 = off.

    Tests switch effects off one at a time to isolate them; nobody tunes them to flatter a
    model. Where each default comes from is documented in `docs/physics.md` and `pipeline/sim/physics.py`.
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
    # Per-unit differences (with part_variation; all three at 0: every unit is the same)
    alignment: float = Field(1.0, ge=0, description="connector alignment: the whole tripod rotated, 5 deg")
    unit_drift: float = Field(1.0, ge=0, description="> 0: each unit its own drift per decade (on/off)")


class SimulateParams(Section):
    """`simulate`: the built-in rig simulator that stands in for a lab.

    Every tissue cast of training is recorded by each of the training `units`; held-out casts by
    a training unit (same-unit held-out) and by each of the `new_units`, which also record a short
    calibration batch each (`pipeline.sim.rig.plan_batches`).
    """

    enabled: bool = True
    seed: int = 20240115
    angles_deg: tuple[float, ...] = (0, 15, 30, 45, 60, 75)
    train_batches: int = Field(3, ge=0, description="tissue casts, recorded at every angle by every unit")
    trials_per_angle: int = Field(3, ge=0, description="per angle, per training cast and training unit")
    heldout_trials_per_angle: int = Field(21, ge=0, description="in each held-out batch of an angle")
    calibration_trials_per_angle: int = Field(1, ge=0, description="in each new unit's calibration batch")
    fsr_rate_hz: float = Field(30.0, gt=0)
    ref_rate_hz: float = Field(100.0, gt=0)
    units: tuple[str, ...] = ("est-sim-001", "est-sim-002", "est-sim-003")  # training units
    new_units: tuple[str, ...] = ("est-sim-101",)  # never in training: held-out and calibration only
    # which estimator design the units are (pipeline/sim/rigs.py: a family other labs could have built)
    rig: str = "default"
    declare_front_end: bool = Field(True, description="write the rig's circuit into batch.yaml")
    # the force axes the simulated reference sensor records (batch.yaml reference.axes): [fz] is a
    # one-axis load cell; the default, all three, writes the files as before
    reference_axes: tuple[Literal["fx", "fy", "fz"], ...] = AXES
    effects: EffectScales = EffectScales()

    @field_validator("reference_axes")
    @classmethod
    def _axes_once_each(cls, value: tuple[str, ...]) -> tuple[str, ...]:
        """Each axis once, at least one; kept in AXES order (the reference files' column order)."""
        if not value or len(set(value)) != len(value):
            raise ValueError(
                f"reference_axes: {list(value)} must name each of {', '.join(AXES)} at most "
                "once, and at least one"
            )
        return tuple(a for a in AXES if a in value)

    @model_validator(mode="after")
    def _check_units(self) -> SimulateParams:
        from needlecue_runtime.vocab import ID_PATTERN  # the rig-log/1 id pattern (sensor.unit_id, batch ids)

        if not self.units:
            raise ValueError("units: at least one training unit is needed")
        for key, ids in (("units", self.units), ("new_units", self.new_units)):
            if bad := [u for u in ids if ID_PATTERN.fullmatch(u) is None]:
                raise ValueError(f"{key}: {bad} do not match the rig-log/1 id pattern {ID_PATTERN.pattern}")
            if len(set(ids)) != len(ids):
                raise ValueError(f"{key}: {list(ids)} lists a unit twice")
        if both := sorted(set(self.units) & set(self.new_units)):
            raise ValueError(f"units and new_units must be disjoint; both list {both}")
        return self


class IngestParams(Section):
    """`ingest`: what counts as a plausible stream."""

    min_rate_hz: float = Field(5.0, gt=0)
    max_rate_hz: float = Field(10_000.0, gt=0)
    min_samples: int = Field(10, ge=2)
    # physical plausibility (pipeline/rig/plausible.py)
    reference_max_n: float = Field(50.0, gt=0, description="the reference sensor's range, |force| in N")
    reference_max_n_by_model: dict[str, float] = Field(
        default_factory=dict, description="range per batch.yaml reference.model, N"
    )
    reference_glitch_n: float = Field(
        5.0, gt=0, description="one sample jumping this far and back is a glitch"
    )
    max_volts: float = Field(5.0, gt=0, description="estimator volts without sensor.vref_v: 0 to this")
    max_trial_factor: float = Field(6.0, gt=1, description="a trial may last this many robot insertions")
    clip_run_s: float = Field(
        0.25, gt=0, description="a stream held at its far extreme this long is clipped (a flat top)"
    )
    max_trial_s: float = Field(
        600.0, gt=0, description="a trial's limit when batch.yaml has no robot programme"
    )


class ResampleParams(Section):
    """`resample`: clock alignment and the common grid."""

    rate_hz: float = Field(30.0, gt=0)
    max_offset_s: float = Field(0.5, gt=0, description="search window for the clock offset, +/-")
    min_quality: float = Field(
        0.7,
        ge=0,
        le=1,
        description="alignment quality (R²) below which a trial is judged against its batch's others",
    )
    offset_step_s: float = Field(0.002, gt=0)
    max_gap_s: float = Field(0.25, gt=0, description="grid points inside longer gaps are dropped")
    lowpass_order: int = Field(4, ge=1)


class SplitParams(Section):
    """`split`: per-angle train/val/test by trial; held-out batches form the external set."""

    seed: int = 0
    val_fraction: float = Field(0.05, ge=0, lt=1)
    test_fraction: float = Field(0.10, ge=0, lt=1)
    external_batches: tuple[str, ...] = ("*heldout*",)


class TrainParams(Section):
    """`train`: the matrix of per-angle models (dvc.yaml: train@<angle>-<kind>)."""

    angles: tuple[float, ...] = (0, 15, 30, 45, 60, 75)
    kinds: tuple[KindName, ...] = KINDS

    @model_validator(mode="before")
    @classmethod
    def _renamed(cls, data: Any) -> Any:
        if isinstance(data, dict) and "models" in data:  # a params.yaml from before the rename
            raise ValueError("train.models is now train.kinds (the model kinds to train): rename the key")
        return data


class EvaluateParams(Section):
    """`evaluate`: which angle gaps are summarised as in the paper's Table II."""

    gaps_deg: tuple[float, ...] = Field((15, 30), min_length=1)


class CalibrateParams(Section):
    """`calibrate`: a new estimator unit's input transform, fitted through the frozen shared models
    from its calibration batch (pipeline/calibration/)."""

    transform: Literal["diagonal", "full"] = "full"  # a gain per channel, or a full channel mix
    offset: bool = False  # also an offset per channel (rest-relative inputs have none to fit)
    ridge: float = Field(0.01, ge=0, description="pull towards the identity (per squared entry)")
    max_iter: int = Field(200, ge=1, description="L-BFGS iterations")
    validate_by_angle: bool = True  # keep the identity unless leave-one-angle-out says the transform helps
    min_trial_s: float = Field(3.0, gt=0, description="a shorter calibration trial is set aside")


class NeedsParams(Section):
    """`needs`: how much data a lab needs (pipeline/needs/): force and cue figures against the training
    insertions per angle, and a new unit's cues against its calibration insertions per angle, by
    subsampling the lab's own data."""

    # training insertions per angle to try: "auto" doubles from 3 up to what every angle has, plus that
    training_insertions: Literal["auto"] | tuple[int, ...] = "auto"
    calibration_insertions: tuple[int, ...] = (1, 2, 3)  # per angle, for a new unit
    cue_target_pct: float = Field(95.0, gt=0, le=100, description="balanced accuracy the advice aims at")
    seed: int = 0  # which insertions a subsample keeps

    @model_validator(mode="after")
    def _check(self) -> NeedsParams:
        for name in ("training_insertions", "calibration_insertions"):
            v = getattr(self, name)
            if v != "auto" and (not v or any(n < 1 for n in v) or list(v) != sorted(set(v))):
                raise ValueError(f"{name} must be increasing counts >= 1, got {list(v)}")
        return self


class RegisterParams(Section):
    """`register`: which models may be deployed and how a champion is chosen."""

    candidates: tuple[KindName, ...] = Field(KINDS, min_length=1)
    min_improvement_pct: float = Field(
        0.0, ge=0, description="NRMSE points (mean of axes) a new version must beat the champion by"
    )


S = TypeVar("S", bound=Section)


def load_section(model: type[S], section: str, path: Path = DEFAULT_PARAMS) -> S:
    """Read one section of params.yaml into its model (missing section = all defaults)."""
    with Path(path).open() as f:
        params = yaml.safe_load(f) or {}
    return model.model_validate(params.get(section) or {})
