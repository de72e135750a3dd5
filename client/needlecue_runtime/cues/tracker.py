"""The cue tracker that runs live in the simulator: one frame at a time, strictly causal.

The paper ends with two rules for the simulator: at the preset angle with the force in range,
tell the trainee to *continue*; off the preset angle, tell them to *correct* (about 15° off) or
to *stop* (30° or more), judged from the predicted force profile. The tracker computes both cue
methods every frame from a *cue pack* (`needlecue_runtime.cues.pack.CuePack`, built by `pipeline.cues.packs`):

- **paper** (profile comparison alone): a running, spread-normalised RMS distance between the
  predicted force and the preset angle's *standard profile*, cut by two calibrated thresholds;
- **combined** (ours): the estimator's own volts say at which angle it is held (the needle's weight
  at rest, then the direction in which the FSRs' conductance moves as the load builds), through
  Gaussian classes per evidence stage read with the estimator unit's own class means and how sure
  they are (`needlecue_runtime.cues.units`: every unit differs), plus the profile's "force in range" check.

A trainee taught the wrong angle is worse off than one taught nothing: the combined method shows an
angle cue only when P(its deviation class) reaches the confidence cross-validated for the way the
estimator knows this unit (`reading_of`); otherwise it shows "none", no angle cue, saying why
(`NO_CUE_REASONS`: an uncalibrated unit, not enough evidence yet, or evidence outside what training
covered). Both methods are debounced (a new cue must hold `debounce_s` before it is shown) with
hysteresis. Numpy, pydantic, the params model and the front end's inversion only: the simulator's client
imports this module and nothing of the training code.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from needlecue_runtime.cues.evidence import Evidence, UnitMap
from needlecue_runtime.cues.pack import (
    CUES,
    METHODS,
    NO_CUE,
    NO_CUE_REASONS,
    READINGS,
    REFERENCE,
    VERDICTS,
    CuePack,
    as_pack,
    cue_for_deviation,
    pack_front_end,
)
from needlecue_runtime.cues.profile import ProfileScore
from needlecue_runtime.cues.reading import UnitReading, distances, log_scores, outside
from needlecue_runtime.cues.states import CueState, Debounce
from needlecue_runtime.cues.units import UnitEvidence, unit_readings, validated_reading
from needlecue_runtime.frontend import Circuit
from needlecue_runtime.params import CuesParams


def _floats(x: Any) -> list[float]:
    return x.tolist() if isinstance(x, np.ndarray) else [float(v) for v in x]


class CueTracker:
    """Frame-by-frame cues for one insertion at one preset angle (strictly causal).

    `method`: "combined" (angle estimate + force-in-range check, the default) or "paper"
    (profile comparison alone). Both are computed every frame; `update` returns the chosen one
    and `states` holds both. `model_kind` picks the paper-method thresholds calibrated for that
    model ("ls", "fnn", "lstm"; default: the first of the pack's `kinds` it has thresholds for, else
    those calibrated on the reference force).
    Call `reset()` at the start of every insertion, with the needle at rest.

    `unit_evidence` is what the estimator knows of the unit (`unit_evidence`), `reading` how it knows
    it (`reading_of`: "training", "calibrated-<k>" or "uncalibrated"), which picks the temperature and
    the confidence a cue needs.

    A pack without an angle estimator (`angle_estimator` null: see `unavailable` in the pack) falls
    back to the paper method for the "combined" cue too, its reason saying that the angle estimate is
    unavailable; a pack without a standard profile or profile thresholds has no paper-method cue (it
    stays on "wait", saying why). `angle_unavailable` / `profile_unavailable` hold those reasons.
    """

    def __init__(
        self,
        pack: CuePack | Mapping[str, Any],
        preset_angle_deg: float,
        *,
        model_kind: str | None = None,
        method: str = "combined",
        unit_evidence: UnitEvidence | None = None,
        front_end: Circuit | None = None,
        reading: str = "training",
        unit_map: UnitMap | None = None,
    ) -> None:
        pack = as_pack(pack)
        if abs(pack.preset_angle_deg - float(preset_angle_deg)) > 1e-6:
            raise ValueError(
                f"this cue pack is for the preset angle {pack.preset_angle_deg:g}°, not {preset_angle_deg:g}°"
            )
        if method not in METHODS:
            raise ValueError(f"method must be one of {METHODS}, got {method!r}")
        self.method = method
        self.preset = float(preset_angle_deg)
        p = CuesParams.model_validate(pack.params)
        self.params = p
        est = pack.estimator
        self.angle_unavailable: str | None = None
        if est is None:
            self.angle_unavailable = "angle estimate unavailable: " + pack.why_missing(
                "angle_estimator", "the cue pack has no angle estimator"
            )
        self.classes = np.asarray(est.classes_deg if est else [], dtype=np.float64)
        self._classes = [float(a) for a in self.classes]
        self._stages = est.stages if est else []
        self._est = est
        self.set_unit(unit_evidence, reading)
        levels = est.levels if est else []
        th = pack.thresholds
        devcls = [
            VERDICTS.index(cue_for_deviation(a - self.preset, th.continue_below_deg, th.stop_from_deg))
            for a in self._classes
        ]
        self._to_dev = np.zeros((len(self._classes), 3))
        self._to_dev[np.arange(len(self._classes)), devcls] = 1.0
        prof = pack.standard_profile
        self._profile = None if prof is None or not prof.mean_n else ProfileScore(prof, p.profile_horizon_s)
        kinds = th.profile
        self.profile_unavailable: str | None = None
        if model_kind is None:
            model_kind = next((k for k in p.kinds if k in kinds), REFERENCE)  # not dict order: JSON sorts
        if self._profile is None:
            self.profile_unavailable = "standard profile unavailable: " + pack.why_missing(
                "standard_profile", "the cue pack has none"
            )
        elif not kinds:
            self.profile_unavailable = "profile thresholds unavailable: " + pack.why_missing(
                f"thresholds.profile.{model_kind}", "the cue pack has none"
            )
        elif model_kind not in kinds:
            raise ValueError(
                f"the cue pack has no profile thresholds for {model_kind!r} (has {sorted(kinds)})"
            )
        self.model_kind = model_kind
        self._t1 = kinds[model_kind].continue_below if model_kind in kinds else math.inf
        self._t2 = kinds[model_kind].stop_from if model_kind in kinds else math.inf
        limit = th.force_limit_n
        self._force_limit2 = float(limit) ** 2 if p.force_check and limit is not None else math.inf
        self._pack_front_end = pack_front_end(pack)
        self._ev = Evidence(
            len(pack.channels),
            levels,
            p.contact_threshold,
            p.contact_samples,
            p.min_rest_s,
            front_end or self._pack_front_end,
            unit_map,
        )
        self._min_stage = min(p.min_stage, len(levels))
        self._deb = Debounce(p.debounce_s)
        self._deb_paper = Debounce(p.debounce_s)
        self.reset()

    def use_front_end(self, front_end: Circuit | None) -> None:
        """Read the loading direction through the unit's own circuit (None: the pack's training
        units'); takes effect at the next insertion (`reset`)."""
        self._ev.front_end = front_end or self._pack_front_end

    def use_unit_map(self, unit_map: UnitMap | None) -> None:
        """Read the unit's conductance through its map (`cue_reading`; None: as it is); takes effect
        at the next insertion (`reset`)."""
        self._ev.unit_map = unit_map

    def reset(self) -> None:
        self._ev.reset()
        self._deb.reset()
        self._deb_paper.reset()
        self._pdev: list[float] | None = None
        self._map = -1
        if self._profile is not None:
            self._profile.reset()
        self._score: float | None = None
        self._alarm = self._outside = False
        self._why: str | None = None
        self._state_key: tuple = ()
        self._paper_key: tuple = ()
        self.states: dict[str, CueState] = {
            m: CueState("wait", None, "reset: waiting for a rest reading") for m in METHODS
        }

    # -- evidence ----------------------------------------------------------------------------
    @property
    def stage(self) -> int:
        return self._ev.stage

    @property
    def contact_t(self) -> float | None:
        return self._ev.contact_t

    @property
    def force_alarm(self) -> bool:
        """The last frame's predicted force was above the pack's force limit."""
        return self._alarm

    @property
    def profile_score(self) -> float | None:
        return self._score

    @property
    def knows_unit(self) -> bool:
        """Whether anything bounds where the unit's classes lie (else: no angle cue, "uncalibrated")."""
        return bool(self._readings) and all(r.known for r in self._readings)

    @property
    def angle_map_deg(self) -> float | None:
        """The most probable trained angle so far, shown or not (None before the rest reading)."""
        return self._classes[self._map] if self._map >= 0 else None

    def posterior(self) -> np.ndarray | None:
        """P(angle) over the pack's trained angles from the evidence so far (None before rest)."""
        return self._judge()[0]

    def _judge(self) -> tuple[np.ndarray | None, bool]:
        """(P(angle), whether the evidence lies outside what training covered) from the evidence so
        far, read through the unit's class means and their uncertainty (None, False before rest)."""
        x = self._ev.features()
        if x is None or not self._readings:
            return None, False
        j = min(self._ev.stage, len(self._readings) - 1)
        reading = self._readings[j]
        d2 = distances(self._precision[j], reading.means, np.asarray(x))
        z = log_scores(d2, reading, self._temp[j])
        e = np.exp(z - z.max())
        far = reading.departs or outside(d2, reading, self._temp[j], self._stages[j].outside_limit)
        return e / e.sum(), far

    # -- one frame ---------------------------------------------------------------------------
    def set_unit(self, evidence: UnitEvidence | None, reading: str = "training") -> None:
        """The estimator unit the angle estimator reads (`unit_evidence`; None: an uncalibrated unit,
        read as the average unit with the training units' spread around it, or not at all when one
        unit trained: then no angle cue is shown), and how it knows it (`reading_of`): the temperature
        and the confidence a cue needs were cross-validated for that case where training allowed."""
        if reading.split("-", 1)[0] not in READINGS:
            raise ValueError(f"a unit is read as one of {READINGS}, not {reading!r}")
        self.unit_known = bool(evidence)
        confidence = self._est.confidence if self._est is not None else {}
        validated = validated_reading(reading, list(confidence))
        if validated is None:  # an uncalibrated unit nothing validated: read as not known at all
            evidence, validated = None, "training"
            self._unvalidated = True
        else:
            self._unvalidated = False
        self.reading = validated
        self._temp = [s.temperatures.get(self.reading, s.temperature) for s in self._stages]
        chosen = confidence.get(self.reading) or confidence.get("training")
        # the P a cue needs: the params' own, or what the estimator chose by cross-validation
        auto = self.params.min_confidence == "auto"
        default = 0.7 if chosen is None else chosen.min_confidence
        self.min_confidence = float(default if auto else self.params.min_confidence)
        self._readings: list[UnitReading] = [
            UnitReading(r.means, np.full(len(r.means), math.inf)) if self._unvalidated else r
            for r in unit_readings(self._stages, self._classes, evidence, reading == "training")
        ]
        self._precision = [np.asarray(s.precision, dtype=np.float64) for s in self._stages]

    def update(self, t_s: float, volts: np.ndarray, force_n: np.ndarray) -> CueState:
        """Feed one frame (volts in the pack's channel order, the model's predicted force in N)."""
        t = float(t_s)
        f = _floats(force_n)
        ev = self._ev
        changed, post = ev.push(t, _floats(volts), f)
        profile = self._profile
        if profile is not None and post:
            for tp, _, fp in post:
                profile.push(tp - ev.contact_t, fp)  # type: ignore[operator]
            self._score = profile.score
        if changed and ev.rest_n and self._readings:
            p, self._outside = self._judge()
            self._pdev = (p @ self._to_dev).tolist()  # type: ignore[operator]
            self._map = int(np.argmax(p))  # type: ignore[arg-type]
        squared = 0.0
        for fk in f:  # the model's targets: fx, fy, fz, or those its reference recorded
            squared += fk * fk
        self._alarm = squared > self._force_limit2

        # combined: angle estimate -> deviation class, force-in-range check
        if self.angle_unavailable is None:
            cue = self._deb.step(t, self._candidate(t))
            key = (cue, self._map, ev.stage, self._alarm, ev.contact_t is not None, self._why)
            if key != self._state_key:
                self._state_key = key
                self.states["combined"] = self._combined_state(cue)

        # paper: profile distance -> thresholds (with hysteresis)
        dp = self._deb_paper
        pc = dp.shown
        if (
            self._score is not None
            and self.profile_unavailable is None
            and t - ev.contact_t >= self.params.min_profile_s - 1e-9  # type: ignore[operator]
        ):
            h = self.params.profile_hysteresis
            t1 = self._t1 * (1 + h if pc == 1 else 1 - h if pc == 2 else 1)
            t2 = self._t2 * (1 + h if pc == 2 else 1 - h if pc == 3 else 1)
            s = self._score
            pc = 1 if s < t1 else (2 if s < t2 else 3)
        pcue = dp.step(t, pc)
        pkey = (pcue, ev.contact_t is not None)
        if pkey != self._paper_key:
            self._paper_key = pkey
            self.states["paper"] = self._paper_state(pcue)
            if self.angle_unavailable is not None:  # the combined cue falls back to the paper's
                paper = self.states["paper"]
                self.states["combined"] = CueState(
                    paper.cue, None, f"{self.angle_unavailable}; paper method: {paper.reason}"
                )
        return self.states[self.method]

    def _candidate(self, t: float) -> int:
        """The cue the evidence supports now (before debouncing); sets `_why` when it is none.

        A cue needs P(its deviation class) >= `min_confidence`, and to beat the shown cue's P by
        `switch_margin` to replace it; a shown cue is withdrawn (no angle cue) once its P falls below
        `min_confidence - switch_margin`. A predicted force out of range is a stop while it lasts."""
        ev, shown, p = self._ev, self._deb.shown, self.params
        if self._alarm:
            return 3
        if self._pdev is None or not ev.rest_ready(t):
            return 0
        self._why = None
        if not self._readings[min(ev.stage, len(self._readings) - 1)].known:
            self._why = "uncalibrated"
        elif ev.stage < self._min_stage:
            self._why = "undecided"
        elif self._outside:
            self._why = "outside"
        else:
            pdv = self._pdev
            best = 0 if pdv[0] >= pdv[1] and pdv[0] >= pdv[2] else (1 if pdv[1] >= pdv[2] else 2)
            showing = 1 <= shown <= 3
            if pdv[best] >= self.min_confidence and (
                not showing or best + 1 == shown or pdv[best] >= pdv[shown - 1] + p.switch_margin
            ):
                return best + 1
            if showing and pdv[shown - 1] >= self.min_confidence - p.switch_margin:
                return shown
            self._why = "undecided" if self.unit_known else "uncalibrated"
        return NO_CUE

    def _combined_state(self, cue: int) -> CueState:
        ev = self._ev
        est = self._classes[self._map] if self._map >= 0 else None
        evidence = "rest reading" + (f" + {ev.stage} loading level(s)" if ev.stage else "")
        if cue == 0:
            return CueState("wait", None, "collecting the rest reading")
        if cue == NO_CUE:
            why = self._why or "undecided"
            best = "" if self._pdev is None else f", best P={max(self._pdev):.2f}"
            return CueState("none", None, f"no angle cue: {NO_CUE_REASONS[why]} ({evidence}{best})", why)
        if self._alarm and cue == 3:
            return CueState("stop", est, "predicted force above the preset angle's range")
        dev = abs(est - self.preset) if est is not None else math.nan
        what = {
            1: "on the preset angle",
            2: "off the preset angle: correct it",
            3: "far off the preset angle: stop",
        }[cue]
        p = self._pdev[cue - 1] if self._pdev is not None else math.nan
        return CueState(
            CUES[cue],
            est,
            f"angle ≈ {est:g}° ({dev:g}° from {self.preset:g}°, P={p:.2f}) from {evidence}: {what}",
        )

    def _paper_state(self, cue: int) -> CueState:
        if cue == 0:
            why = "waiting for contact" if self._ev.contact_t is None else "comparing the profile"
            if self.profile_unavailable is not None:
                why = f"no cue: {self.profile_unavailable}"
            return CueState("wait", None, why)
        return CueState(
            CUES[cue],
            None,
            f"predicted force vs the standard profile of {self.preset:g}°: "
            f"{['', 'within', 'off', 'far off'][cue]} its range",
        )
