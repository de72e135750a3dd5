"""The simulator's live force model: `ForceClient` runs one fetched model sample by sample.

A client holds one `Model` (`needlecue_client.model`: a checked folder, its ONNX graph run by
onnxruntime, nothing unpickled), the unit's calibration decided for it (`needlecue_client.calibration`) and
the per-insertion state `step` writes into (pre-allocated arrays, the cue tracker when the model
carries a cue pack). A client made by `from_registry` follows its alias (`needlecue_client.follow`):
`reset()` asks the registry where the alias points at most once every `poll_s` seconds and, if it
moved, swaps in the new `Model` between insertions (`refresh()` does it on demand); `step()` never
talks to the registry.

Estimator units: every unit differs, and the shared models read a unit through its calibration (an
input transform per model kind, fitted through those very models: `pipeline.calibration`). A client
named a unit (`unit_id`) applies the unit's registered calibration, `needle-unit-<unit_id>@current`,
when it was made with the loaded model (its checkpoint sha256). Otherwise the client is *uncalibrated*:
an `UncalibratedUnit` warning (and one log warning) says why and how to fix it, the force is the
model's on the raw unit, and no cues are given (the cue pack was fitted on the training units), unless
`cues_uncalibrated=True`. A swap to a new model, or a new calibration of the unit, re-decides it.
"""

from __future__ import annotations

import math
import sys
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from needlecue_client.cache import poll_alias
from needlecue_client.calibration import (
    CALIBRATE_FIX,
    NO_UNIT,
    Decision,
    Source,
    about,
    decide,
    given,
    registered,
)
from needlecue_client.copies import ModelNotFound
from needlecue_client.follow import Follower
from needlecue_client.model import Model, StreamMismatch, log
from needlecue_runtime.features import ModelInputs, RestReading, unit_inputs
from needlecue_runtime.registry import store

if TYPE_CHECKING:
    from needlecue_runtime.cues.states import CueState

__all__ = [
    "CALIBRATE_FIX",
    "DEFAULT_POLL_S",
    "NO_UNIT",
    "ForceClient",
    "Frame",
    "StreamMismatch",
    "UncalibratedUnit",
]

DEFAULT_POLL_S = 60.0
_PACKAGE_DIR = str(Path(__file__).resolve().parent)


class UncalibratedUnit(UserWarning):
    """The client runs its model without the estimator unit's calibration (no unit named, the unit not
    registered, its calibration made with other models, ...): force on the raw unit, and no cues unless
    `cues_uncalibrated=True`. The message names the unit, the reason and the fix."""


def _outside_stacklevel() -> int:
    """The `warnings.warn` stacklevel of the first caller outside this package (the user's line)."""
    frame, level = sys._getframe(1), 1
    while frame is not None and frame.f_code.co_filename.startswith(_PACKAGE_DIR):
        frame, level = frame.f_back, level + 1
    return level


@dataclass(frozen=True, slots=True)
class Frame:
    """One step's output: the sample's time, the force in N, one value per axis of the client's `targets`
    in that order ((fx, fy, fz), or (fz,) for a model of a load cell's fz alone), and the cue (None
    without cues)."""

    t_s: float
    force_n: np.ndarray
    cue: CueState | None


class ForceClient:
    """One registered force model, run sample by sample on the live estimator stream.

    Attributes of the model (`needlecue_client.model.Model`): `angle_deg` (the preset angle it was
    trained at), `kind`, `channels` (the order `step` takes volts in), `targets` (the force axes `step`
    gives, in its order: those the reference recorded, e.g. ("fx", "fy", "fz") or ("fz",)), `rate_hz`,
    `window` (samples of history, 1 for ls/fnn), `version` (version.json of a fetched folder: name, version,
    alias, run_id, ...; None for a bare folder; it changes when `reset` or `refresh` swaps in a new
    version of the alias), `metadata` (the whole `needlecue` block), `model_dir`.

    The estimator unit: `unit_id` (None if not named), `calibrated` (whether the unit's calibration
    applies to this model and is applied to every sample), `calibration` (where the applied document
    came from: the version.json of `needle-unit-<unit_id>@current` as fetched, or {unit_id, path,
    calibration_sha256} / {unit_id} for a document given to `from_dir`; None when uncalibrated),
    `uncalibrated_reason` (why not, None when calibrated).
    """

    def __init__(
        self,
        model: Model,
        source: Source,
        *,
        unit_id: str | None = None,
        cues_uncalibrated: bool = False,
        follower: Follower | None = None,
    ) -> None:
        """`model` run for estimator unit `unit_id` with the calibration in `source` if it applies;
        `follower`: the alias it follows (`from_registry`). Made by `from_dir` and `from_registry`."""
        self._follower = follower
        self._stream: tuple[tuple[str, ...], float, float] | None = None  # the last stream checked
        self.unit_id = unit_id
        self._cues_uncalibrated = bool(cues_uncalibrated)
        self._decision: Decision | None = None  # None: the unit is not decided yet
        self._unit_seen = source.seen  # the registered document last fetched
        self._use(model)
        self._decide_unit(source)

    def _use(self, model: Model) -> None:
        """Run `model` from now on: its cue tracker and per-frame state, made afresh."""
        self._model = model
        self._n = len(model.channels)
        # Pre-allocated per-frame state: `step` writes into these arrays instead of allocating. The
        # graph reads the raw window, the rest reading at each of its samples and the unit (as data).
        self._volts = np.zeros((1, *model.input_shape), dtype=np.float64)
        self._rests = np.zeros_like(self._volts)
        names = model.metadata["graph_inputs"]
        unit = unit_inputs(None, None, self._n)
        volts = np.ones(1)  # `step` takes volts: one volt per reading unit
        self._feed = dict(zip(names, (self._volts, self._rests, volts, *unit), strict=True))
        self._outputs = [model.session.get_outputs()[0].name]
        self._rest = RestReading(model.inputs.rest_s, self._n)
        self._tracker: Any = model.cue_tracker()
        self._cues_on = False  # decided with the unit (`_decide_unit`)
        self.reset(poll=False)

    @classmethod
    def from_dir(
        cls,
        model_dir: Path,
        *,
        calibration: Path | str | Mapping[str, Any] | None = None,
        unit_id: str | None = None,
        cues_uncalibrated: bool = False,
        unverified: bool = False,
    ) -> ForceClient:
        """The client of a fetched model folder (MLmodel + model.onnx), refused (`ModelRefused`)
        unless its graph and description are what was registered (`unverified`: run anyway, after a
        loud warning).

        `calibration`: the unit's calibration document (a calibration.json path, or the document
        itself); its unit is the client's `unit_id` (a different `unit_id` is a ValueError). Without
        one, or when it was made with other models, the client is uncalibrated: an `UncalibratedUnit`
        warning, and no cues unless `cues_uncalibrated`."""
        model = Model.open(Path(model_dir), unverified)
        source, unit_id = given(calibration, unit_id)
        return cls(model, source, unit_id=unit_id, cues_uncalibrated=cues_uncalibrated)

    @classmethod
    def from_registry(
        cls,
        angle_deg: float,
        alias: str = store.CHAMPION,
        *,
        unit_id: str | None = None,
        cues_uncalibrated: bool = False,
        poll_s: float | None = DEFAULT_POLL_S,
        **fetch_kwargs: Any,
    ) -> ForceClient:
        """Fetch (or reuse the cached) `models:/needle-force-<angle>@<alias>` and load it, with the
        calibration of estimator unit `unit_id`, `models:/needle-unit-<unit_id>@current` (cached beside
        the models, used offline like them).

        Calibrated iff that calibration was made with this very model; otherwise (no `unit_id`, the unit
        not registered, a calibration made with other models, offline without a cached calibration) an
        `UncalibratedUnit` warning, the force without calibration and no cues unless `cues_uncalibrated`.

        The client follows the alias: `reset()` asks the registry where it points at most once every
        `poll_s` seconds (None or 0: never by itself; `refresh(force=True)` still does) and swaps in a
        new version (see `refresh`); it also picks up a new calibration of the unit. It polls and fetches
        from the store and cache of this first fetch (`tracking_uri`, `cache_dir`: the defaults are read
        now).
        """
        follower = Follower.start(angle_deg, alias, fetch_kwargs, poll_s)
        if unit_id is not None:
            store.unit_model_name(unit_id)  # a malformed id is the caller's error, not "unregistered"
        model = follower.fetch()
        source = registered(unit_id, follower.fetch_kwargs)
        return cls(model, source, unit_id=unit_id, cues_uncalibrated=cues_uncalibrated, follower=follower)

    # --- the model -------------------------------------------------------------------------------------

    @property
    def model(self) -> Model:
        """The model run now (a swap replaces it)."""
        return self._model

    model_dir = property(lambda self: self._model.model_dir)
    metadata = property(lambda self: self._model.metadata)
    version = property(lambda self: self._model.version)
    kind = property(lambda self: self._model.kind)
    angle_deg = property(lambda self: self._model.angle_deg)
    channels = property(lambda self: self._model.channels)
    targets = property(lambda self: self._model.targets)
    rate_hz = property(lambda self: self._model.rate_hz)
    window = property(lambda self: self._model.window)
    name = property(lambda self: self._model.name, doc="`needle-force-30 v3 (lstm)`, or the folder.")

    @property
    def inputs(self) -> ModelInputs:
        return self._model.inputs

    # --- the estimator unit ----------------------------------------------------------------------------

    @property
    def calibrated(self) -> bool:
        return self._decision is not None and self._decision.calibrated

    @property
    def calibration(self) -> dict[str, Any] | None:
        return None if self._decision is None else self._decision.calibration

    @property
    def uncalibrated_reason(self) -> str | None:
        return None if self._decision is None else self._decision.reason

    def _registered_unit(self) -> Source:
        assert self._follower is not None, (
            "only a client made by from_registry fetches its unit's calibration"
        )
        source = registered(self.unit_id, self._follower.fetch_kwargs)
        self._unit_seen = source.seen or self._unit_seen
        return source

    def _decide_unit(self, source: Source) -> bool:
        """Decide whether the unit's calibration in `source` applies to the model run now and set the
        transform and cues; warn when uncalibrated (once per reason). True if the calibration in use
        changed."""
        decision, first = decide(self._model, source), self._decision is None
        before = None if first else (self.calibrated, self.uncalibrated_reason, self.calibration)
        self._decision = decision
        names = self._model.metadata["graph_inputs"]
        unit = unit_inputs(decision.transform, decision.circuit, self._n)
        self._feed.update(zip(names[3:], unit, strict=True))
        self._cues_on = self._tracker is not None and (decision.calibrated or self._cues_uncalibrated)
        if self._tracker is not None:  # what the angle estimator knows of this unit, if anything
            from needlecue_runtime.cues.units import cue_reading, reading_of, unit_evidence

            self._tracker.use_front_end(decision.circuit)
            pack = self._model.cue_pack
            # its calibration insertions' evidence, and the map its conductance is read through, if any
            evidence, unit_map = (
                cue_reading(pack, decision.doc.cue_section())
                if decision.calibrated and decision.doc
                else (None, None)
            )
            self._tracker.use_unit_map(unit_map)
            self._tracker.set_unit(
                unit_evidence(pack, self.unit_id, evidence), reading_of(pack, self.unit_id, evidence)
            )
        after = (self.calibrated, self.uncalibrated_reason, self.calibration)
        if not self.calibrated and (first or before is None or before[:2] != after[:2]):
            self._warn_uncalibrated()
        elif self.calibrated and not first and before != after:
            log.info(
                "%s: estimator unit %s calibrated (%s)", self.name, self.unit_id, about(self.calibration)
            )
        return not first and before != after

    def _warn_uncalibrated(self) -> None:
        who = "the estimator unit" if self.unit_id is None else f"estimator unit {self.unit_id!r}"
        cues = "and its cues anyway (cues_uncalibrated=True)" if self._cues_uncalibrated else "and no cues"
        fix = (
            CALIBRATE_FIX
            if self.unit_id is not None
            else f"name the unit (unit_id=...); to calibrate it, {CALIBRATE_FIX}"
        )
        message = (
            f"{who} is not calibrated for {self.name} at {self.angle_deg:g}°: {self.uncalibrated_reason}. "
            f"The client gives the model's force without the unit's calibration {cues}. Fix: {fix}."
        )
        warnings.warn(UncalibratedUnit(message), stacklevel=_outside_stacklevel())
        log.warning("%s", message)

    def _refresh_unit(self) -> bool:
        """A registry client's unit: if `@current` moved, fetch and apply the new calibration (True if
        the calibration in use changed)."""
        if self._follower is None or self.unit_id is None:
            return False
        name = store.unit_model_name(self.unit_id)
        try:
            mv = poll_alias(name, store.UNIT_ALIAS, self._follower.fetch_kwargs["tracking_uri"])
        except (store.RegistryUnreachable, ModelNotFound) as e:
            log.debug(
                "%s@%s: not polled (%s); keeping the calibration decided before", name, store.UNIT_ALIAS, e
            )
            return False
        if (str(mv.version), mv.source) == self._unit_seen:
            return False
        return self._decide_unit(self._registered_unit())

    # --- following the alias ---------------------------------------------------------------------------

    @property
    def has_cues(self) -> bool:
        """Whether `step` gives cues: the model has a cue pack, and the unit is calibrated for it (or
        `cues_uncalibrated` was asked for)."""
        return self._cues_on

    @property
    def knows_unit(self) -> bool:
        """Whether the angle estimator knows where this unit's classes lie: a training unit, a unit whose
        calibration insertions it read, or an uncalibrated one that the training units bound (False:
        no angle cue for it, "uncalibrated unit")."""
        return self._tracker is not None and self._tracker.knows_unit

    @property
    def contact_t(self) -> float | None:
        """When the cue tracker saw the needle touch the tissue in this insertion (None before, or
        without cues): the time origin of the standard profile."""
        return None if self._tracker is None or not self._cues_on else self._tracker.contact_t

    @property
    def standard_profile(self) -> dict[str, Any] | None:
        """The preset angle's standard force profile from the cue pack ({axes, dt_s, mean_n, sd_n, ...},
        time since contact), or None."""
        pack = self._model.cue_pack
        return pack.get("standard_profile") if isinstance(pack, Mapping) else None

    def __repr__(self) -> str:
        return f"ForceClient({self.name}, angle_deg={self.angle_deg:g}, channels={list(self.channels)})"

    def check_stream(self, channels: Sequence[str], rate_hz: float, rel_tol: float = 0.05) -> None:
        """Raise `StreamMismatch` unless the stream delivers the model's channels (same order) at its
        rate (within `rel_tol`)."""
        self._model.check_stream(channels, rate_hz, rel_tol)
        self._stream = (tuple(channels), float(rate_hz), rel_tol)  # a new version must fit it too

    def refresh(self, force: bool = False) -> bool:
        """Ask the registry where the alias points now and, if it moved, fetch that version and swap it
        in; True if a new model was loaded (`version`, `kind`, `window`, ... are then the new one's), or
        a new calibration of the unit. A new model is checked against the unit's calibration again (a
        champion the calibration was not made with leaves the client uncalibrated, with a warning); when
        the model stays, a unit whose `@current` moved gets its new calibration.

        Without `force` only once `poll_s` has passed since the last poll (`reset()` calls it so); with
        it, now, whatever the interval (which restarts). A swap starts a fresh insertion: call it between
        insertions. Never raises for the registry or the new model: False, the current model kept and
        - an unreachable registry (or a vanished alias): a warning, once until a poll succeeds again;
        - a new version that does not fit the stream checked with `check_stream` (without one: this
          model's channels and rate), is for other targets, or cannot be loaded: an error; it is not
          tried again until the alias moves (or `force`).
        A client made from a folder has nothing to follow: always False.
        """
        follower = self._follower
        if follower is None or not (force or follower.due()):
            return False
        follower.polled()
        try:
            found = follower.where()
        except (store.RegistryUnreachable, ModelNotFound) as e:
            follower.failed(e, self.name)
            return False
        if found == self._model.version_key or (found == follower.refused and not force):
            return self._refresh_unit()
        return self._swap(found)

    def poll_soon(self) -> None:
        """Have the next `reset()` ask the registry at once, whatever `poll_s` says: a registry webhook
        said an alias moved (`needlecue_client.webhook`). The swap itself still waits for the reset."""
        if self._follower is not None:
            self._follower.poll_soon()

    @property
    def followed(self) -> tuple[str, ...]:
        """The registered models this client follows: its angle's, and its unit's calibrations."""
        if self._follower is None:
            return ()
        names = [self._follower.model_name]
        if self.unit_id is not None:
            names.append(store.unit_model_name(self.unit_id))
        return tuple(names)

    def _swap(self, found: tuple[str, Any]) -> bool:
        """Fetch the alias's version `found`, check it like the first and take its place (see refresh)."""
        follower = self._follower
        assert follower is not None
        name, before = follower.model_name, (self.version or {}).get("version")
        try:
            new = follower.fetch()
        except (store.RegistryUnreachable, ModelNotFound) as e:
            follower.failed(e, self.name)
            return False
        except Exception as e:  # a broken new version must not stop the simulator: keep the one that works
            follower.refused = found
            log.error(
                "%s: %s v%s cannot be loaded, keeping v%s: %s: %s",
                name,
                follower.alias,
                found[0],
                before,
                type(e).__name__,
                e,
            )
            return False
        key = new.version_key
        if key == self._model.version_key:  # fetch fell back to the cached copy, or the alias moved back
            return self._refresh_unit()
        problem = self._model.misfit(new, self._stream)
        if problem is not None:
            follower.refused = key
            log.error(
                "%s: %s v%s refused, keeping v%s: %s", name, follower.alias, key and key[0], before, problem
            )
            return False
        self._use(new)  # the one reference that changes; the unit is decided again for it below
        follower.refused = None
        log.info("%s: %s v%s -> v%s", name, follower.alias, before, key and key[0])
        self._decide_unit(self._registered_unit())
        return True

    # --- running -------------------------------------------------------------------------------------

    def reset(self, poll: bool = True) -> None:
        """Start a new insertion: forget the window's history and the cue state. A client made by
        `from_registry` first polls its alias if `poll_s` has passed (see `refresh`): a new version is
        swapped in here, never mid-insertion. `poll=False` skips that poll (a caller whose insertion has
        already begun, and that polled when the last one ended)."""
        if poll and self._follower is not None and self._follower.due():
            self.refresh()
        self._frames = 0
        self._last_t = math.nan
        self._rest.reset()
        if self._tracker is not None:
            self._tracker.reset()

    def step(self, volts: Sequence[float] | np.ndarray, t_s: float | None = None) -> Frame:
        """One estimator sample (volts in `channels` order) -> the force now (one value per `targets`
        axis) and the cue.

        `t_s` defaults to the previous sample's time plus 1 / rate_hz (0 for the first)."""
        if len(volts) != self._n:
            raise ValueError(f"step takes {self._n} volts ({', '.join(self.channels)}), got {len(volts)}")
        sample = np.asarray(volts, dtype=np.float64)
        if not np.isfinite(sample).all():
            raise ValueError(f"non-finite volts {list(sample)} for channels {list(self.channels)}")
        if t_s is None:
            t_s = 0.0 if self._frames == 0 else self._last_t + 1.0 / (self.rate_hz or 1.0)
        rest = self._rest.push(float(t_s), sample)
        for window, now in ((self._volts[0], sample), (self._rests[0], rest)):
            if len(window) > 1 and self._frames > 0:
                window[:-1] = window[1:]  # slide the window by one sample (numpy handles the overlap)
                window[-1] = now
            else:
                window[...] = now  # first sample of an insertion fills the window, as training padded it
        force = self._model.session.run(self._outputs, self._feed)[0][0].astype(np.float64)
        self._frames += 1
        self._last_t = float(t_s)
        cue = self._tracker.update(self._last_t, sample, force) if self._cues_on else None
        return Frame(self._last_t, force, cue)
