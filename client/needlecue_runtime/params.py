"""The params sections the simulator's runtime reads as well as the pipeline: the base of every section,
a model kind's name, what a model reads (`InputParams`) and the cues (`CuesParams`). `pipeline.config`
holds the rest of params.yaml and re-exports these, so a stage reads every section from one module."""

from __future__ import annotations

import itertools
import math
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from needlecue_runtime.vocab import KINDS

KindName = Literal[KINDS]  # type: ignore[valid-type]  # a model kind's name, one of vocab.KINDS: a typo fails loudly


class Section(BaseModel):
    """Base of every params section: immutable, and unknown keys are errors."""

    model_config = ConfigDict(frozen=True, extra="forbid")


class InputParams(Section):
    """`<model>.inputs`: what a model reads (client/needlecue_runtime/features.py): volts as read, or the
    FSR conductance behind them, either relative to the trial's rest reading; `auto` chooses among
    them by validation on the data (pipeline/modelling/choice.py), a kind pins one. The circuit that
    turns volts into conductance is not a param: it is the estimator's, declared with its batches
    (batch.yaml `sensor.front_end`)."""

    kind: Literal["auto", "volts", "rest_volts", "conductance", "rest_conductance"] = "auto"
    rest_s: float = Field(0.5, gt=0, description="seconds at a trial's start that define its rest reading")


AUTO_EVIDENCE_LEVELS = 9  # cues.evidence_levels: auto


class CuesParams(Section):
    """`cues`: the simulator's angle cues (pipeline/cues/)."""

    kinds: tuple[KindName, ...] = Field(KINDS, min_length=1)
    # deviation bands: |angle - preset| below continue_below_deg -> continue, from stop_from_deg -> stop
    continue_below_deg: float = Field(7.5, gt=0)
    stop_from_deg: float = Field(22.5, gt=0)
    # contact: any channel's |log(v / rest mean)| above contact_threshold for contact_samples frames
    contact_threshold: float = Field(0.02, gt=0)
    contact_samples: int = Field(2, ge=1)
    min_rest_s: float = Field(0.3, ge=0, description="rest reading needed before a contact or a cue")
    # angle estimator: one LDA per evidence stage (rest, then each loading level reached)
    # "auto": AUTO_EVIDENCE_LEVELS levels spread over the loading most training trials reach
    # (pipeline.cues.trials.loading_levels), or the levels themselves
    evidence_levels: Literal["auto"] | tuple[float, ...] = "auto"
    lda_shrinkage: Literal["auto"] | float = "auto"
    # a unit's trials at an angle count n against this weight of the average unit's shifted mean
    unit_template_weight: Literal["auto"] | float = "auto"
    calibrate_temperature: bool = True
    min_stage: int = Field(0, ge=0, description="evidence stage needed to leave wait (0: rest reading)")
    # P(deviation class) a cue needs: "auto" is the least that keeps the cross-validated share of
    # insertion frames with a wrong cue at or under max_wrong (pipeline.cues.confidence), or the number
    min_confidence: Literal["auto"] | float = "auto"
    max_wrong: float = Field(0.01, gt=0, lt=1, description="the wrong-cue frame share 'auto' aims at")
    switch_margin: float = Field(0.3, ge=0, le=1)
    debounce_s: float = Field(0.2, ge=0)
    # the paper's standard profile and its comparison
    profile_dt_s: float = Field(0.1, gt=0)
    profile_horizon_s: float = Field(10.0, gt=0)
    profile_floor_n: float = Field(0.05, gt=0, description="added in quadrature to the profile's spread")
    min_profile_s: float = Field(1.0, ge=0, description="seconds after contact before the profile cues")
    profile_hysteresis: float = Field(0.05, ge=0, lt=1)
    # force in range (combined method)
    force_check: bool = True
    force_margin: float = Field(1.5, gt=0)
    cue_within_s: float = Field(3.0, gt=0, description="a cue is right if right, and staying so, by then")

    @model_validator(mode="after")
    def _check(self) -> CuesParams:
        if self.stop_from_deg <= self.continue_below_deg:
            raise ValueError("stop_from_deg must exceed continue_below_deg")
        lv = self.evidence_levels
        if lv == "auto":
            lv = (1.0,) * AUTO_EVIDENCE_LEVELS
        elif any(x <= 0 for x in lv) or any(b <= a for a, b in itertools.pairwise(lv)):
            raise ValueError(f"evidence_levels must be 'auto' or positive and increasing, got {list(lv)}")
        if isinstance(self.lda_shrinkage, float) and not 0 <= self.lda_shrinkage <= 1:
            raise ValueError("lda_shrinkage is 'auto' or a float in [0, 1]")
        if isinstance(self.min_confidence, float) and not 0 <= self.min_confidence <= 1:
            raise ValueError("min_confidence is 'auto' or a float in [0, 1]")
        k = self.unit_template_weight
        if isinstance(k, float) and not (math.isfinite(k) and k > 0):
            # the reading divides by it (a unit's departure variance is 1/k) and weighs means by it
            raise ValueError("unit_template_weight is 'auto' or a finite float > 0")
        if self.min_stage > len(lv):
            raise ValueError(f"min_stage {self.min_stage} exceeds the {len(lv)} evidence levels")
        return self
