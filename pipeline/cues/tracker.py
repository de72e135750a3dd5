"""The cue tracker that runs live in the simulator: one frame at a time, strictly causal.

The paper ends with two rules for the simulator: at the preset angle with the force in range,
tell the trainee to *continue*; off the preset angle, tell them to *correct* (about 15° off) or
to *stop* (30° or more), judged from the predicted force profile. The tracker computes both cue
methods every frame from a *cue pack* (`pipeline.cues.fit.build_cue_pack`):

- **paper** (profile comparison alone): a running, spread-normalised RMS distance between the
  predicted force and the preset angle's *standard profile*, cut by two calibrated thresholds;
- **combined** (ours): the estimator's own volts say at which angle it is held (the needle's weight
  at rest, then the direction in which the FSRs' conductance moves as the load builds), through
  Gaussian classes per evidence stage read with the estimator unit's own class means and how sure
  they are (`pipeline.cues.reading`: every unit differs), plus the profile's "force in range" check.

A trainee taught the wrong angle is worse off than one taught nothing: the combined method shows an
angle cue only when P(its deviation class) reaches the confidence cross-validated for the way the
estimator knows this unit (`reading_of`); otherwise it shows "none", no angle cue, saying why
(`NO_CUE_REASONS`: an uncalibrated unit, not enough evidence yet, or evidence outside what training
covered). Both methods are debounced (a new cue must hold `debounce_s` before it is shown) with
hysteresis. Numpy, the params model and the front end's inversion only: the simulator's client imports
this module and nothing of the training code.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from pipeline.config import CuesParams
from pipeline.cues.reading import Cell, UnitReading, distances, log_scores, outside, read_unit
from pipeline.frontend import Circuit, conductance_us, conductance_us_of_frame, declared, legacy_divider
from pipeline.modelling.features import MIN_CONDUCTANCE_US
from pipeline.vocab import format_problem

FORMAT = "needlecue-cues/5"  # 5: a unit's class means with their uncertainty (4: levels in the signal read)
# "wait": the rest reading is being collected; "none": no angle cue, the evidence does not decide
CUES = ("wait", "continue", "correct", "stop", "none")
VERDICTS = CUES[1:4]  # the cues a deviation maps to
NO_CUE = CUES.index("none")
# why there is no angle cue (CueState.no_cue), in the trainee's words
NO_CUE_REASONS = {
    "uncalibrated": "uncalibrated unit",
    "undecided": "not enough evidence yet",
    "outside": "outside what training covered",
}
METHODS = ("combined", "paper")
DEVIATION_GROUPS = ("0", "15", "30", ">=45")
REFERENCE = "reference"  # profile thresholds calibrated on the reference force (no model)
MIN_VOLTS = 1e-3  # floor before taking logs (an unloaded FSR reads a few mV)


UnitEvidence = Mapping[str, Mapping[str, Any]]  # {angle: {"n": [per stage], "means": [per stage]}}


READINGS = ("training", "calibrated", "uncalibrated")  # how the estimator knows a unit (`reading_of`)


def reading_of(pack: Mapping[str, Any], unit_id: str | None, calibration: UnitEvidence | None) -> str:
    """How the angle estimator knows a unit: by its calibration insertions ("calibrated-<k>", k the
    fewest insertions it has at an angle), by its training trials in the pack ("training"), or not at
    all ("uncalibrated"). Each has its own cross-validated temperature and confidence in the pack
    where training allowed (`pipeline.cues.fit`); `CueTracker.set_unit` picks the nearest."""
    if calibration:
        k = min((int(e["n"][0]) for e in calibration.values() if e.get("n")), default=1)
        return f"calibrated-{max(k, 1)}"
    units = (pack.get("angle_estimator") or {}).get("units") or {}
    return "training" if unit_id is not None and unit_id in units else "uncalibrated"


def validated_reading(reading: str, validated: Sequence[str]) -> str | None:
    """The reading whose cross-validated numbers apply to `reading`: itself if validated; for a unit
    calibrated from k insertions per angle, the deepest validated calibration of at most k
    insertions (else the shallowest, else "training": one training unit, nothing could be left
    out); for an uncalibrated unit, None unless it was validated (too few training units to leave
    one out and still bound it: it gets no angle cue)."""
    if reading in validated:
        return reading
    if reading == "uncalibrated":
        return None
    if reading.startswith("calibrated-"):
        k = int(reading.rsplit("-", 1)[1])
        depths = sorted(int(r.rsplit("-", 1)[1]) for r in validated if r.startswith("calibrated-"))
        if depths:
            return f"calibrated-{max([d for d in depths if d <= k] or [depths[0]])}"
    return "training"


def unit_evidence(
    pack: Mapping[str, Any], unit_id: str | None, calibration: UnitEvidence | None = None
) -> UnitEvidence | None:
    """What the angle estimator knows of an estimator unit (`pipeline.cues.unit_evidence`): its calibration's
    evidence when given, else a training unit's from the pack, else None (an uncalibrated unit: the
    estimator's average unit)."""
    if calibration:
        return calibration
    units = (pack.get("angle_estimator") or {}).get("units") or {}
    return units.get(unit_id) if unit_id is not None else None


def calibration_evidence(pack: Mapping[str, Any], cues: Mapping[str, Any] | None) -> UnitEvidence | None:
    """The evidence in a unit calibration's `cues` section ({"levels", "evidence"}) if it was gathered
    at the loading levels of this pack's angle estimator, else None (features at other levels are
    not the estimator's: the unit is then read as the average one)."""
    if not cues or not cues.get("evidence"):
        return None
    levels = np.asarray((pack.get("angle_estimator") or {}).get("levels") or [], dtype=np.float64)
    mine = np.asarray(cues.get("levels") or [], dtype=np.float64)[: len(levels)]
    # as stored: the document keeps 6 decimals (an absolute 5e-7), the pack 6 significant digits
    same = len(mine) == len(levels) and np.allclose(mine, levels, rtol=1e-5, atol=1e-6)
    return cues["evidence"] if same else None


def cue_reading(
    pack: Mapping[str, Any], cues: Mapping[str, Any] | None
) -> tuple[UnitEvidence | None, UnitMap | None]:
    """How the angle estimator reads a calibrated unit, from its calibration's `cues` section: (its
    evidence, the map its conductance is read through, or None: as it is).

    As it is, unless its calibration insertions depart from the training units' layout at some
    evidence stage (`departing_levels`: no angle cue there) and, read through the unit's map on its
    conductance (`cues.mapped`: the map of the model kind that fits it best, `pipeline.calibration.
    unit`), they depart nowhere. A unit that departs nowhere is read as it is: through the force
    models' map it would be read in a layout cross-validation never saw, and on the family's units
    that cost more wrong cues than the 2 % a trainee may see. A map that leaves the unit departing
    somewhere is not taken either: measured once, it added wrong cues (docs/units.md, "A new unit
    read through a map")."""
    evidence = calibration_evidence(pack, cues)
    if not evidence or not cues or not cues.get("mapped"):
        return evidence, None
    mapped = cues["mapped"]
    through = mapped.get("evidence")  # gathered at the same levels, which `evidence` has matched
    if through and departing_levels(pack, evidence) and not departing_levels(pack, through):
        return through, UnitMap.of(mapped)
    return evidence, None


def _cells(classes: Sequence[float], evidence: UnitEvidence | None, j: int) -> list[Cell]:
    """The unit's cells at evidence stage j: per class, its trials that reached the stage."""
    cells = []
    for c, a in enumerate(classes):
        e = (evidence or {}).get(f"{float(a):g}")
        if e and len(e["n"]) > j and e["n"][j] > 0:
            cells.append((c, float(e["n"][j]), np.asarray(e["means"][j], dtype=np.float64)))
    return cells


def unit_readings(
    stages: Sequence[Mapping[str, Any]],
    classes: Sequence[float],
    evidence: UnitEvidence | None,
    trained: bool = False,
) -> list[UnitReading]:
    """How each evidence stage reads the unit of `evidence` (None: an uncalibrated unit): its class
    means and their uncertainty (`pipeline.cues.reading.read_unit`), with the stage's
    `template_weight` and `offset_spread`. A unit training did not see (not `trained`) is also
    tested, with the stage's precision, for departing from the training units' layout, and a
    departure is kept at later stages that fewer of the unit's classes reach: a stage's features hold
    every earlier stage's, and a departure seen with an angle's cell cannot be undone by a stage
    without it (four cells of the middle angles can fit a shift where six did not). A later stage
    with as many cells judges anew: it has more features to judge by."""
    out: list[UnitReading] = []
    widest = 0  # the most cells an earlier stage departed with
    for j, stage in enumerate(stages):
        cells = _cells(classes, evidence, j)
        r = read_unit(
            np.asarray(stage["means"], dtype=np.float64),
            cells,
            stage.get("template_weight"),
            stage.get("offset_spread"),
            None if trained else np.asarray(stage["precision"], dtype=np.float64),
        )
        if not r.departs and widest > len(cells):
            r = replace(r, departs=True)
        if r.departs:
            widest = max(widest, len(cells))
        out.append(r)
    return out


def departing_levels(pack: Mapping[str, Any], evidence: UnitEvidence) -> list[int]:
    """The evidence stages (0: the rest reading, j: the j-th loading level) at which a calibrated
    unit's insertions sit unlike any shift of the training units' layout (`UnitReading.departs`,
    carried forward by `unit_readings`): there it gets no angle cue ("outside what training
    covered")."""
    est = pack.get("angle_estimator") or {}
    readings = unit_readings(est.get("stages") or [], est.get("classes_deg") or [], evidence)
    return [j for j, r in enumerate(readings) if r.departs]


def cue_for_deviation(dev_deg: float, continue_below: float = 7.5, stop_from: float = 22.5) -> str:
    """continue / correct / stop for an absolute angle deviation in degrees."""
    d = abs(dev_deg)
    return "continue" if d < continue_below else ("correct" if d < stop_from else "stop")


def _floats(x: Any) -> list[float]:
    return x.tolist() if isinstance(x, np.ndarray) else [float(v) for v in x]


@dataclass(frozen=True)
class UnitMap:
    """A calibrated unit's map on its FSRs' conductance, g' = g A^T + b (µS), as its calibration
    fitted it for the force models (`cue_reading` says when the cues read a unit through it).
    Floored: a map must not open a loaded FSR."""

    matrix: np.ndarray
    offset: np.ndarray

    def apply(self, g: np.ndarray) -> np.ndarray:
        return np.maximum(g @ self.matrix.T + self.offset, MIN_CONDUCTANCE_US)

    @classmethod
    def of(cls, d: Mapping[str, Any]) -> UnitMap:
        """A stored map ({"matrix", "offset"})."""
        return cls(np.asarray(d["matrix"], dtype=np.float64), np.asarray(d["offset"], dtype=np.float64))


# ---------------------------------------------------------------------------------------------
# Causal evidence: rest reading, contact, loading snapshots (shared by build and tracker)
# ---------------------------------------------------------------------------------------------


class Evidence:
    """What the estimator's volts say so far. `push` one frame at a time; True if the features
    changed (the rest mean moved, or a new loading level was reached)."""

    __slots__ = (
        "_rest_signal",
        "contact_i",
        "contact_t",
        "front_end",
        "levels",
        "min_rest_s",
        "n_ch",
        "n_confirm",
        "pending",
        "rest",
        "rest_n",
        "rest_sum",
        "snaps",
        "t_first",
        "thr",
        "unit_map",
    )

    def __init__(
        self,
        n_ch: int,
        levels: Sequence[float],
        thr: float,
        n_confirm: int,
        min_rest_s: float,
        front_end: Circuit | None,
        unit_map: UnitMap | None = None,
    ):
        self.n_ch, self.levels, self.thr = n_ch, tuple(levels), thr
        self.n_confirm, self.min_rest_s, self.front_end = n_confirm, min_rest_s, front_end
        self.unit_map = unit_map
        self.reset()

    def reset(self) -> None:
        self.rest_sum = [0.0] * self.n_ch
        self.rest_n = 0
        self.t_first: float | None = None
        self.pending: list[tuple[float, list[float], Any]] = []
        self.contact_t: float | None = None
        self.contact_i = -1  # frame index of contact (counted from reset)
        self.rest: list[float] | None = None  # rest mean, frozen at contact
        self._rest_signal: np.ndarray | None = None  # its signal (conductance or volts)
        self.snaps: list[list[float]] = []  # the unit loading direction at each level reached

    @property
    def stage(self) -> int:
        return len(self.snaps)

    def rest_mean(self) -> list[float] | None:
        if self.rest is not None:
            return self.rest
        if self.rest_n == 0:
            return None
        n = self.rest_n
        return [s / n for s in self.rest_sum]

    def rest_ready(self, t: float) -> bool:
        return self.contact_t is not None or (
            self.t_first is not None and t - self.t_first >= self.min_rest_s - 1e-9 and self.rest_n > 0
        )

    def signal(self, volts: Sequence[float]) -> np.ndarray:
        """What the evidence reads of `volts`: the FSRs' conductance through the declared circuit (the
        same for every design of front end), else the volts themselves; through the unit's map on its
        conductance where it is read through one (`cue_reading`)."""
        if self.front_end is None:
            return np.asarray(volts, dtype=np.float64)
        if isinstance(volts, list):  # one frame (every frame after contact): the fast path
            g = np.array(conductance_us_of_frame(volts, self.front_end))
        else:
            g = conductance_us(np.asarray(volts, dtype=np.float64), self.front_end)
        return g if self.unit_map is None else self.unit_map.apply(g)

    def rest_signal(self) -> np.ndarray:
        """The signal of the rest mean (frozen at contact)."""
        if self._rest_signal is None:
            self._rest_signal = self.signal(self.rest)  # type: ignore[arg-type]
        return self._rest_signal

    def loading(self, signal: np.ndarray) -> Any:
        """How far `signal` (one frame, or frames along the first axis) has moved from rest: the norm
        of its log ratio to the rest signal, what the levels are set on. After contact only."""
        return np.sqrt(np.sum(np.log(signal / self.rest_signal()) ** 2, axis=-1))

    def features(self) -> list[float] | None:
        """log of the rest signal per channel, then the unit direction of the signal's change since
        rest at each level reached (the direction, not the size: how hard the tissue pushes back is
        not the angle's business)."""
        rest = self.rest_mean()
        if rest is None:
            return None
        out = np.log(self.signal(rest)).tolist()
        for s in self.snaps:
            out.extend(s)
        return out

    def push(self, t: float, v: list[float], extra: Any = None, i: int = -1) -> tuple[bool, list]:
        """Feed one frame. Returns (features changed, frames that became post-contact now: the
        confirming run, [(t, v, extra)], empty unless contact was just confirmed or already on)."""
        v = [x if x > MIN_VOLTS else MIN_VOLTS for x in v]
        if self.contact_t is not None:
            return self._snap(v), [(t, v, extra)]
        if self.t_first is None:
            self.t_first = t
        if not self.rest_ready(t):
            self._add_rest(v)
            return True, []
        n = self.rest_n
        dev = max(abs(math.log(x * n / s)) for x, s in zip(v, self.rest_sum, strict=True))
        if dev > self.thr:
            self.pending.append((t, v, extra, i))
            if len(self.pending) < self.n_confirm:
                return False, []
            self.rest = [s / n for s in self.rest_sum]
            self.contact_t, self.contact_i = self.pending[0][0], self.pending[0][3]
            changed = False
            run = []
            for tp, vp, ep, _ in self.pending:
                changed |= self._snap(vp)
                run.append((tp, vp, ep))
            self.pending = []
            return changed, run
        for _, vp, _, _ in self.pending:  # the run broke: those were rest after all
            self._add_rest(vp)
        self.pending = []
        self._add_rest(v)
        return True, []

    def _add_rest(self, v: list[float]) -> None:
        rs = self.rest_sum
        for k, x in enumerate(v):
            rs[k] += x
        self.rest_n += 1

    def _snap(self, v: list[float]) -> bool:
        if len(self.snaps) >= len(self.levels):
            return False
        # A level is reached by how far the signal moved from rest (the norm of its log ratio), and
        # the direction is the signal's: above actuation an FSR's conductance grows in proportion to
        # its share of the load, whatever its cast-in preload (docs/units.md, "How the cue estimator
        # reads a unit"). Without a declared circuit there is no conductance: the volts stand in.
        now = self.signal(v)
        norm = float(self.loading(now))
        if norm < self.levels[len(self.snaps)]:
            return False
        dg = now - self.rest_signal()
        size = float(np.sqrt(np.sum(dg * dg))) or 1.0
        direction = (dg / size).tolist()
        while len(self.snaps) < len(self.levels) and norm >= self.levels[len(self.snaps)]:
            self.snaps.append(direction)
        return True


@dataclass(frozen=True)
class CueState:
    cue: str  # "wait" | "continue" | "correct" | "stop" | "none" (no angle cue)
    angle_est_deg: float | None  # the estimate behind a shown angle cue (None when none is shown)
    reason: str
    no_cue: str | None = None  # with "none": a key of NO_CUE_REASONS


class _Debounce:
    """A new candidate cue is shown once it has been the candidate for `hold_s` seconds."""

    __slots__ = ("hold", "pending", "shown", "since")

    def __init__(self, hold_s: float) -> None:
        self.hold = hold_s - 1e-9
        self.reset()

    def reset(self) -> None:
        self.shown, self.pending, self.since = 0, -1, 0.0

    def step(self, t: float, candidate: int) -> int:
        if candidate == self.shown:
            self.pending = -1
        elif candidate != self.pending:
            self.pending, self.since = candidate, t
        if self.pending >= 0 and t - self.since >= self.hold:
            self.shown, self.pending = self.pending, -1
        return self.shown


def pack_format_problem(pack: Any) -> str | None:
    """None if `pack` is a cue pack of this version's format, else why not."""
    found = pack.get("format") if isinstance(pack, Mapping) else type(pack).__name__
    return format_problem(found, FORMAT, "cue pack", "`dvc repro` builds and registers a new one")


def pack_front_end(pack: Mapping[str, Any]) -> Circuit | None:
    """The circuit a pack's training units declared (its loading directions are in their FSRs'
    conductance), or None (in volts). A pack from before circuits were data names its divider in
    its params."""
    if "front_end" in pack:
        return declared(pack["front_end"])
    old = (pack.get("params") or {}).get("divider")
    return None if old is None else legacy_divider(old)


def check_pack(pack: Mapping[str, Any]) -> None:
    problem = pack_format_problem(pack)
    if problem:
        raise ValueError(problem)
    for key in (
        "preset_angle_deg",
        "channels",
        "standard_profile",
        "angle_estimator",
        "thresholds",
        "params",
    ):
        if key not in pack:
            raise ValueError(f"the cue pack lacks {key!r}")


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
        pack: Mapping[str, Any],
        preset_angle_deg: float,
        *,
        model_kind: str | None = None,
        method: str = "combined",
        unit_evidence: UnitEvidence | None = None,
        front_end: Circuit | None = None,
        reading: str = "training",
        unit_map: UnitMap | None = None,
    ) -> None:
        check_pack(pack)
        if abs(float(pack["preset_angle_deg"]) - float(preset_angle_deg)) > 1e-6:
            raise ValueError(
                f"this cue pack is for the preset angle {pack['preset_angle_deg']:g}°, "
                f"not {preset_angle_deg:g}°"
            )
        if method not in METHODS:
            raise ValueError(f"method must be one of {METHODS}, got {method!r}")
        self.method = method
        self.preset = float(preset_angle_deg)
        p = CuesParams.model_validate({k: v for k, v in pack["params"].items() if k != "divider"})
        self.params = p
        missing = pack.get("unavailable") or {}
        est = pack["angle_estimator"]
        if est is not None and not est.get("stages"):
            est = None
        self.angle_unavailable: str | None = None
        if est is None:
            self.angle_unavailable = "angle estimate unavailable: " + str(
                missing.get("angle_estimator", "the cue pack has no angle estimator")
            )
        self.classes = np.asarray(est["classes_deg"] if est else [], dtype=np.float64)
        self._classes = [float(a) for a in self.classes]
        self._stages = est["stages"] if est else []
        self._est = est
        self.set_unit(unit_evidence, reading)
        levels = est["levels"] if est else []
        th = pack["thresholds"]
        devcls = [
            VERDICTS.index(cue_for_deviation(a - self.preset, th["continue_below_deg"], th["stop_from_deg"]))
            for a in self._classes
        ]
        self._to_dev = np.zeros((len(self._classes), 3))
        self._to_dev[np.arange(len(self._classes)), devcls] = 1.0
        prof = pack["standard_profile"] or {"mean_n": [], "sd_n": [], "floor_n": 1.0, "dt_s": 1.0}
        self._mean = [tuple(r) for r in prof["mean_n"]]
        floor2 = float(prof["floor_n"]) ** 2
        self._isd = [tuple(1.0 / math.sqrt(s * s + floor2) for s in r) for r in prof["sd_n"]]
        self._dt = float(prof["dt_s"])
        self._n_prof = len(self._mean)
        self._n_axes = len(self._mean[0]) if self._mean else 0  # the profile's axes, the model's targets
        self._horizon = p.profile_horizon_s + 1e-9
        kinds = th["profile"] or {}
        self.profile_unavailable: str | None = None
        if model_kind is None:
            model_kind = next((k for k in p.kinds if k in kinds), REFERENCE)  # not dict order: JSON sorts
        if not self._n_prof:
            self.profile_unavailable = "standard profile unavailable: " + str(
                missing.get("standard_profile", "the cue pack has none")
            )
        elif not kinds:
            self.profile_unavailable = "profile thresholds unavailable: " + str(
                missing.get(f"thresholds.profile.{model_kind}", "the cue pack has none")
            )
        elif model_kind not in kinds:
            raise ValueError(
                f"the cue pack has no profile thresholds for {model_kind!r} (has {sorted(kinds)})"
            )
        self.model_kind = model_kind
        self._t1 = float(kinds[model_kind]["continue_below"]) if model_kind in kinds else math.inf
        self._t2 = float(kinds[model_kind]["stop_from"]) if model_kind in kinds else math.inf
        limit = th.get("force_limit_n")
        self._force_limit2 = float(limit) ** 2 if p.force_check and limit is not None else math.inf
        self._pack_front_end = pack_front_end(pack)
        self._ev = Evidence(
            len(pack["channels"]),
            levels,
            p.contact_threshold,
            p.contact_samples,
            p.min_rest_s,
            front_end or self._pack_front_end,
            unit_map,
        )
        self._min_stage = min(p.min_stage, len(levels))
        self._deb = _Debounce(p.debounce_s)
        self._deb_paper = _Debounce(p.debounce_s)
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
        self._z2, self._nz = 0.0, 0
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
        far = reading.departs or outside(d2, reading, self._temp[j], self._stages[j].get("outside_limit"))
        return e / e.sum(), far

    def _accumulate(self, t: float, f: Any) -> None:
        tau = t - self._ev.contact_t  # type: ignore[operator]
        if tau > self._horizon:
            return
        g = int(tau / self._dt + 0.5)
        if g >= self._n_prof:
            g = self._n_prof - 1
        m, s = self._mean[g], self._isd[g]
        z2 = 0.0
        for fk, mk, sk in zip(f, m, s, strict=True):  # the profile's axes, the model's targets
            d = (fk - mk) * sk
            z2 += d * d
        self._z2 += z2
        self._nz += 1

    # -- one frame ---------------------------------------------------------------------------
    def set_unit(self, evidence: UnitEvidence | None, reading: str = "training") -> None:
        """The estimator unit the angle estimator reads (`unit_evidence`; None: an uncalibrated unit,
        read as the average unit with the training units' spread around it, or not at all when one
        unit trained: then no angle cue is shown), and how it knows it (`reading_of`): the temperature
        and the confidence a cue needs were cross-validated for that case where training allowed."""
        if reading.split("-", 1)[0] not in READINGS:
            raise ValueError(f"a unit is read as one of {READINGS}, not {reading!r}")
        self.unit_known = bool(evidence)
        confidence = (self._est or {}).get("confidence") or {}
        validated = validated_reading(reading, list(confidence))
        if validated is None:  # an uncalibrated unit nothing validated: read as not known at all
            evidence, validated = None, "training"
            self._unvalidated = True
        else:
            self._unvalidated = False
        self.reading = validated
        self._temp = [
            float((s.get("temperatures") or {}).get(self.reading, s["temperature"])) for s in self._stages
        ]
        chosen = confidence.get(self.reading) or confidence.get("training") or {}
        # the P a cue needs: the params' own, or what the estimator chose by cross-validation
        auto = self.params.min_confidence == "auto"
        self.min_confidence = float(chosen.get("min_confidence", 0.7) if auto else self.params.min_confidence)
        self._readings: list[UnitReading] = [
            UnitReading(r.means, np.full(len(r.means), math.inf)) if self._unvalidated else r
            for r in unit_readings(self._stages, self._classes, evidence, reading == "training")
        ]
        self._precision = [np.asarray(s["precision"], dtype=np.float64) for s in self._stages]

    def update(self, t_s: float, volts: np.ndarray, force_n: np.ndarray) -> CueState:
        """Feed one frame (volts in the pack's channel order, the model's predicted force in N)."""
        t = float(t_s)
        f = _floats(force_n)
        ev = self._ev
        changed, post = ev.push(t, _floats(volts), f)
        if self._n_prof:
            for tp, _, fp in post:
                self._accumulate(tp, fp)
        if self._nz:
            self._score = math.sqrt(self._z2 / (self._n_axes * self._nz))
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
