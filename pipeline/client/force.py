"""The simulator's live force model: `ForceClient` runs one fetched model sample by sample.

A client reads a model folder (the `needlecue` block of its MLmodel and its model.onnx) and runs the
ONNX graph with onnxruntime, one frame at a time on pre-allocated arrays, with the cue tracker beside
it when the model carries a cue pack; nothing is unpickled. A client made by `from_registry` follows
its alias: `reset()` asks the registry where the alias points at most once every `poll_s` seconds and,
if it moved, swaps in the new version between insertions (`refresh()` does it on demand); `step()`
never talks to the registry. onnxruntime and the cue tracker are imported inside the functions that
need them.

Estimator units: every unit differs, and the shared models read a unit through its calibration (an
input transform per model kind, fitted through those very models: `pipeline.calibration`). A client
named a unit (`unit_id`) applies the unit's registered calibration, `needle-unit-<unit_id>@current`,
when it was made with the loaded model (its checkpoint sha256). Otherwise the client is *uncalibrated*:
an `UncalibratedUnit` warning (and one log warning) says why and how to fix it, the force is the
model's on the raw unit, and no cues are given (the cue pack was fitted on the training units), unless
`cues_uncalibrated=True`. A swap to a new model, or a new calibration of the unit, re-decides it.
"""

from __future__ import annotations

import logging
import math
import sys
import time
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from pipeline.calibration.document import FILE as UNIT_FILE
from pipeline.calibration.document import FORMAT as UNIT_FORMAT
from pipeline.calibration.document import read_unit, transform_for
from pipeline.client.cache import (
    ModelNotFound,
    default_cache_dir,
    fetch,
    fetch_unit,
    poll_alias,
    read_version,
)
from pipeline.client.folder import ONNX_FILE, open_model
from pipeline.modelling.features import InputTransform, StreamFeatures, spec_of
from pipeline.registry import store
from pipeline.rig.frontend import declared
from pipeline.vocab import DEPLOY_FORMAT, angle_name, file_sha256

if TYPE_CHECKING:
    from pipeline.cues.tracker import CueState

# One logger for the whole client, named as before it was split into modules (log configs keep working).
log = logging.getLogger("pipeline.client")

DEFAULT_POLL_S = 60.0
CALIBRATE_FIX = "record a calibration batch with the unit and run `needlecue calibrate BATCH_DIR`"
NO_UNIT = "no estimator unit named (unit_id)"
_PACKAGE_DIR = str(Path(__file__).resolve().parent)


class StreamMismatch(ValueError):
    """The estimator stream's channels or rate are not those the model was trained on."""


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


def _monotonic() -> float:
    """The clock of the alias polls (a function of its own, so that tests can move it)."""
    return time.monotonic()


@dataclass(frozen=True, slots=True)
class Frame:
    """One step's output: the sample's time, the force (fx, fy, fz) in N and the cue (None without cues)."""

    t_s: float
    force_n: np.ndarray
    cue: CueState | None


@dataclass(slots=True)
class _Follow:
    """How a registry client was fetched, and when it next asks the registry where its alias points."""

    angle_deg: float
    alias: str
    fetch_kwargs: dict[str, Any]  # cache_dir and tracking_uri, fixed when the client was made
    poll_s: float | None
    next_poll: float  # on the `_monotonic` clock; inf: no automatic polls
    refused: tuple[str, Any] | None = None  # (version, source) refused: not tried again until the alias moves
    failing: bool = False  # the last poll could not reach the registry (it was warned about once)


class ForceClient:
    """One registered force model, run sample by sample on the live estimator stream.

    Attributes: `angle_deg` (the preset angle the model was trained at), `kind`, `channels` (the order
    `step` takes volts in), `targets`, `rate_hz`, `window` (samples of history, 1 for ls/fnn),
    `version` (version.json of a fetched folder: name, version, alias, run_id, ...; None for a bare
    folder; it changes when `reset` or `refresh` swaps in a new version of the alias), `metadata` (the
    whole `needlecue` block), `model_dir`.

    The estimator unit: `unit_id` (None if not named), `calibrated` (whether the unit's calibration
    applies to this model and is applied to every sample), `calibration` (where the applied document
    came from: the version.json of `needle-unit-<unit_id>@current` as fetched, or {unit_id, path,
    calibration_sha256} / {unit_id} for a document given to `from_dir`; None when uncalibrated),
    `uncalibrated_reason` (why not, None when calibrated).
    """

    def __init__(
        self,
        model_dir: Path,
        *,
        calibration: Path | str | Mapping[str, Any] | None = None,
        unit_id: str | None = None,
        cues_uncalibrated: bool = False,
        unverified: bool = False,
    ) -> None:
        """The model of a folder (see `from_dir`, which this is)."""
        self._load(Path(model_dir), unverified)
        doc, info = _given_calibration(calibration)
        if doc is not None:
            if unit_id is not None and doc.get("unit_id") != unit_id:
                raise ValueError(f"the calibration given is of unit {doc.get('unit_id')!r}, not {unit_id!r}")
            unit_id = str(doc["unit_id"])
        self._init_unit(unit_id, cues_uncalibrated)
        problem = None
        if doc is None:
            problem = NO_UNIT if unit_id is None else "no calibration document was given (calibration=...)"
        self._apply_unit(doc, info, problem)

    @classmethod
    def _bare(cls, model_dir: Path) -> ForceClient:
        """The model alone, its unit not decided yet (`from_registry` and a swap decide it)."""
        client = cls.__new__(cls)
        client._load(Path(model_dir))
        return client

    def _load(self, model_dir: Path, unverified: bool = False) -> None:
        """Check the model folder (`pipeline.client.folder.open_model`), make the ONNX session, cue
        tracker and per-frame state."""
        self._follow: _Follow | None = None  # set by from_registry
        self._stream: tuple[tuple[str, ...], float, float] | None = None  # the last stream checked
        self.model_dir = Path(model_dir)
        self.metadata, self._session = open_model(self.model_dir, unverified=unverified)
        meta: dict[str, Any] = self.metadata
        self.kind: str = meta["kind"]
        self.angle_deg: float = float(meta["angle_deg"])
        self.channels: tuple[str, ...] = tuple(meta["channels"])
        self.targets: tuple[str, ...] = tuple(meta["targets"])
        self.rate_hz: float | None = None if meta.get("rate_hz") is None else float(meta["rate_hz"])
        self.window: int = int(meta["window"])
        self.inputs = spec_of(meta.get("inputs"))  # deploy/1 models read raw volts
        self.version: dict[str, Any] | None = read_version(self.model_dir)
        inputs, outputs = self._session.get_inputs(), self._session.get_outputs()
        shape = (self.window, len(self.channels)) if self.kind == "lstm" else (len(self.channels),)
        if [i.name for i in inputs] != [meta["input"]] or tuple(inputs[0].shape[1:]) != shape:
            found = [(i.name, i.shape) for i in inputs]
            raise ValueError(
                f"{self.model_dir / ONNX_FILE}: inputs {found} do not match its MLmodel metadata "
                f"({meta['input']!r} of shape (batch, {', '.join(map(str, shape))}))"
            )
        # Pre-allocated per-frame state: `step` writes into these arrays instead of allocating.
        self._x = np.zeros((1, *shape), dtype=np.float32)
        self._feed = {meta["input"]: self._x}
        self._outputs = [outputs[0].name]
        self._n = len(self.channels)
        self._features = StreamFeatures(self.inputs, self._n)
        self._transform: InputTransform | None = None  # the unit's calibration, if it applies
        self._cues_on = False  # decided with the unit (`_apply_unit`)
        self._tracker: Any = None
        pack = meta.get("cues")
        if pack is not None:
            from pipeline.cues.tracker import CueTracker, pack_format_problem

            problem = pack_format_problem(pack)
            if problem:  # force without cues beats no force at all
                log.warning("%s: no cues: %s", self.model_dir, problem)
            elif list(pack.get("channels", self.channels)) != list(self.channels):
                raise ValueError(
                    f"{self.model_dir}: the cue pack reads channels {pack.get('channels')}, "
                    f"the model {list(self.channels)}"
                )
            else:
                # the paper-method thresholds were calibrated per model kind: use this model's if there
                kinds = (pack.get("thresholds") or {}).get("profile") or {}
                self._tracker = CueTracker(
                    pack, self.angle_deg, model_kind=self.kind if self.kind in kinds else None
                )
        self.reset()

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
        return cls(
            Path(model_dir),
            calibration=calibration,
            unit_id=unit_id,
            cues_uncalibrated=cues_uncalibrated,
            unverified=unverified,
        )

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
        not registered, a calibration made with other models, a needlecue-deploy/1 model, offline without
        a cached calibration) an `UncalibratedUnit` warning, the force without calibration and no cues
        unless `cues_uncalibrated`.

        The client follows the alias: `reset()` asks the registry where it points at most once every
        `poll_s` seconds (None or 0: never by itself; `refresh(force=True)` still does) and swaps in a
        new version (see `refresh`); it also picks up a new calibration of the unit. It polls and fetches
        from the store and cache of this first fetch (`tracking_uri`, `cache_dir`: the defaults are read
        now).
        """
        if poll_s is not None and not poll_s >= 0:
            raise ValueError(f"poll_s is seconds >= 0 or None, got {poll_s!r}")
        if unit_id is not None:
            store.unit_model_name(unit_id)  # a malformed id is the caller's error, not "unregistered"
        kwargs = dict(fetch_kwargs)
        kwargs["tracking_uri"] = kwargs.get("tracking_uri") or store.tracking_uri()
        kwargs["cache_dir"] = Path(kwargs.get("cache_dir") or default_cache_dir()).expanduser()
        client = cls._bare(fetch(angle_deg, alias, **kwargs))
        client._follow = _Follow(
            angle_deg, alias, kwargs, poll_s or None, _monotonic() + poll_s if poll_s else math.inf
        )
        client._init_unit(unit_id, cues_uncalibrated)
        client._apply_unit(*client._unit_source())
        return client

    # --- the estimator unit ---------------------------------------------------------------------------

    def _init_unit(self, unit_id: str | None, cues_uncalibrated: bool) -> None:
        self.unit_id: str | None = unit_id
        self._cues_uncalibrated = bool(cues_uncalibrated)
        self.calibrated = False
        self.calibration: dict[str, Any] | None = None
        self.uncalibrated_reason: str | None = None
        # (version, source) of the unit's last fetched document: a poll that finds it again fetches nothing
        self._unit_seen: tuple[str, Any] | None = None
        self._unit_decided = False

    def _unit_source(self) -> tuple[dict[str, Any] | None, dict[str, Any] | None, str | None]:
        """(document, its version.json, None), or (None, None, why there is none): the registered
        calibration of the unit, fetched (or its cached copy when offline)."""
        follow = self._follow
        if self.unit_id is None:
            return None, None, NO_UNIT
        assert follow is not None, "only a client made by from_registry fetches its unit's calibration"
        name = store.unit_model_name(self.unit_id)
        try:
            folder = fetch_unit(self.unit_id, **follow.fetch_kwargs)
            doc, info = read_unit(folder / UNIT_FILE), read_version(folder)
        except ModelNotFound:
            return None, None, f"it has no registered calibration ({name}@{store.UNIT_ALIAS})"
        except store.RegistryUnreachable as e:
            return None, None, f"the registry cannot be reached and no calibration is cached ({e})"
        except ValueError as e:  # a broken registered document
            return None, None, f"its registered calibration cannot be used: {e}"
        if info is not None:
            self._unit_seen = (str(info.get("version")), info.get("source"))
        return doc, info, None

    def _transform_of(self, doc: Mapping[str, Any]) -> tuple[InputTransform | None, str | None]:
        """The unit's transform for this model, or (None, why it does not apply)."""
        fmt = self.metadata.get("format")
        if fmt != DEPLOY_FORMAT:
            return None, f"the model is a {fmt} model, made before unit calibrations (it reads raw volts)"
        angle, sha = angle_name(self.angle_deg), str(self.metadata.get("checkpoint_sha256"))
        transform = transform_for(doc, self.kind, angle, sha)
        if transform is None:
            transforms = doc.get("transforms") or {}
            made = (transforms.get(self.kind) or {}).get("models") or {}
            if self.kind not in transforms:
                found = ", ".join(sorted(transforms)) or "none"
                return None, f"its calibration has no transform for {self.kind} models (it has {found})"
            if angle not in made:
                return None, f"its calibration was not made with a {self.kind} model at {angle}°"
            return None, (
                f"its calibration was made with another {self.kind} model at {angle}° (checkpoint "
                f"{str(made[angle])[:12]}, this model's {sha[:12]}): calibrate the unit for the new model"
            )
        if transform.n != len(self.channels):
            return (
                None,
                f"its {self.kind} transform maps {transform.n} inputs, the model reads {len(self.channels)}",
            )
        return transform, None

    def _apply_unit(
        self, doc: Mapping[str, Any] | None, info: dict[str, Any] | None, problem: str | None
    ) -> bool:
        """Decide whether the unit's document `doc` applies to the loaded model (else `problem` says why
        there is none) and set the transform and cues; warn when uncalibrated (once per reason). True if
        the calibration in use changed."""
        transform, reason = (None, problem) if doc is None else self._transform_of(doc)
        before = (self.calibrated, self.uncalibrated_reason, self.calibration)
        first = not self._unit_decided
        self._unit_decided = True
        self._transform = transform
        self.calibrated = transform is not None
        # a calibrated unit that declared its circuit is read through it (else the model's)
        circuit = declared((doc or {}).get("front_end")) if self.calibrated else None
        spec = self.inputs.through(circuit)
        if spec != self._features.spec:  # the unit is decided before its first insertion's samples
            self._features = StreamFeatures(spec, self._n)
        if self._tracker is not None:
            self._tracker.use_front_end(circuit)
        self.calibration = dict(info or {}) if self.calibrated else None
        self.uncalibrated_reason = None if self.calibrated else (reason or "unknown")
        self._cues_on = self._tracker is not None and (self.calibrated or self._cues_uncalibrated)
        if self._tracker is not None:  # what the angle estimator knows of this unit, if anything
            from pipeline.cues.tracker import calibration_evidence, unit_evidence

            pack = self.metadata["cues"]
            evidence = calibration_evidence(pack, (doc or {}).get("cues")) if self.calibrated else None
            self._tracker.set_unit(unit_evidence(pack, self.unit_id, evidence))
        after = (self.calibrated, self.uncalibrated_reason, self.calibration)
        if not self.calibrated and (first or before[:2] != after[:2]):
            self._warn_uncalibrated()
        elif self.calibrated and not first and before != after:
            log.info(
                "%s: estimator unit %s calibrated (%s)", self.name, self.unit_id, _about(self.calibration)
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
        follow = self._follow
        if follow is None or self.unit_id is None:
            return False
        name = store.unit_model_name(self.unit_id)
        try:
            mv = poll_alias(name, store.UNIT_ALIAS, follow.fetch_kwargs["tracking_uri"])
        except (store.RegistryUnreachable, ModelNotFound) as e:
            log.debug(
                "%s@%s: not polled (%s); keeping the calibration decided before", name, store.UNIT_ALIAS, e
            )
            return False
        if (str(mv.version), mv.source) == self._unit_seen:
            return False
        return self._apply_unit(*self._unit_source())

    @property
    def name(self) -> str:
        """`needle-force-30 v3 (lstm)`, or the folder for an unregistered copy."""
        if self.version:
            return f"{self.version.get('name')} v{self.version.get('version')} ({self.kind})"
        return f"{self.model_dir} ({self.kind})"

    @property
    def has_cues(self) -> bool:
        """Whether `step` gives cues: the model has a cue pack, and the unit is calibrated for it (or
        `cues_uncalibrated` was asked for)."""
        return self._cues_on

    @property
    def contact_t(self) -> float | None:
        """When the cue tracker saw the needle touch the tissue in this insertion (None before, or
        without cues): the time origin of the standard profile."""
        return None if self._tracker is None or not self._cues_on else self._tracker.contact_t

    @property
    def standard_profile(self) -> dict[str, Any] | None:
        """The preset angle's standard force profile from the cue pack ({axes, dt_s, mean_n, sd_n, ...},
        time since contact), or None."""
        pack = self.metadata.get("cues")
        return pack.get("standard_profile") if isinstance(pack, Mapping) else None

    def __repr__(self) -> str:
        return f"ForceClient({self.name}, angle_deg={self.angle_deg:g}, channels={list(self.channels)})"

    def check_stream(self, channels: Sequence[str], rate_hz: float, rel_tol: float = 0.05) -> None:
        """Raise `StreamMismatch` unless the stream delivers the model's channels (same order) at its
        rate (within `rel_tol`)."""
        problems = []
        if tuple(channels) != self.channels:
            missing = [c for c in self.channels if c not in channels]
            extra = [c for c in channels if c not in self.channels]
            detail = f"missing {missing}" if missing else ""
            detail += (", " if detail and extra else "") + (f"extra {extra}" if extra else "")
            problems.append(
                f"channels: the model reads {list(self.channels)}, the stream has {list(channels)} "
                f"({detail or 'same channels in another order: pass volts in the model order'})"
            )
        if self.rate_hz is not None and not (
            math.isfinite(rate_hz) and abs(rate_hz - self.rate_hz) <= rel_tol * self.rate_hz
        ):
            problems.append(
                f"rate: the model was trained at {self.rate_hz:.3g} Hz, the stream runs at {rate_hz:.3g} Hz "
                f"(tolerance {rel_tol:.0%})"
            )
        if problems:
            raise StreamMismatch(
                f"stream does not fit {self.name}, angle {self.angle_deg:g}°: " + "; ".join(problems)
            )
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
        follow = self._follow
        if follow is None:
            return False
        now = _monotonic()
        if not force and now < follow.next_poll:
            return False
        follow.next_poll = now + follow.poll_s if follow.poll_s else math.inf
        name = store.model_name(follow.angle_deg)
        try:  # one quick metadata request: no retries, short timeout
            mv = poll_alias(name, follow.alias, follow.fetch_kwargs["tracking_uri"])
        except (store.RegistryUnreachable, ModelNotFound) as e:
            self._poll_failed(e)
            return False
        if follow.failing:
            log.info("%s@%s: the registry answers again", name, follow.alias)
            follow.failing = False
        found = (str(mv.version), mv.source)
        if found == self._version_key() or (found == follow.refused and not force):
            return self._refresh_unit()
        return self._swap(found)

    def poll_soon(self) -> None:
        """Have the next `reset()` ask the registry at once, whatever `poll_s` says: a registry webhook
        said an alias moved (`pipeline.client.webhook`). The swap itself still waits for the reset."""
        if self._follow is not None:
            self._follow.next_poll = -math.inf

    @property
    def followed(self) -> tuple[str, ...]:
        """The registered models this client follows: its angle's, and its unit's calibrations."""
        if self._follow is None:
            return ()
        names = [store.model_name(self._follow.angle_deg)]
        if self.unit_id is not None:
            names.append(store.unit_model_name(self.unit_id))
        return tuple(names)

    def _version_key(self) -> tuple[str, Any] | None:
        """(version, source) of the loaded model: source tells two stores' "v1" apart."""
        v = self.version
        return None if v is None else (str(v.get("version")), v.get("source"))

    def _poll_failed(self, error: Exception) -> None:
        follow = self._follow
        assert follow is not None
        when = f"next try in {follow.poll_s:g} s" if follow.poll_s else "no automatic polls"
        level = logging.DEBUG if follow.failing else logging.WARNING
        log.log(
            level,
            "%s@%s: cannot poll the registry (%s); keeping %s, %s",
            store.model_name(follow.angle_deg),
            follow.alias,
            error,
            self.name,
            when,
        )
        follow.failing = True

    def _swap(self, found: tuple[str, Any]) -> bool:
        """Fetch the alias's version `found`, check it like the first and take its place (see refresh)."""
        follow = self._follow
        assert follow is not None
        name = store.model_name(follow.angle_deg)
        before = (self.version or {}).get("version")
        try:
            new = type(self)._bare(fetch(follow.angle_deg, follow.alias, **follow.fetch_kwargs))
        except (store.RegistryUnreachable, ModelNotFound) as e:
            self._poll_failed(e)
            return False
        except Exception as e:  # a broken new version must not stop the simulator: keep the one that works
            follow.refused = found
            log.error(
                "%s: %s v%s cannot be loaded, keeping v%s: %s: %s",
                name,
                follow.alias,
                found[0],
                before,
                type(e).__name__,
                e,
            )
            return False
        key = new._version_key()
        if key == self._version_key():  # fetch fell back to the cached copy, or the alias moved back
            return self._refresh_unit()
        problem = self._misfit(new)
        if problem is not None:
            follow.refused = key
            log.error(
                "%s: %s v%s refused, keeping v%s: %s", name, follow.alias, key and key[0], before, problem
            )
            return False
        keep = {"_follow": follow, "_stream": self._stream}
        vars(self).update(vars(new))  # the model's attributes; the unit's stay, decided again below
        vars(self).update(keep)
        follow.refused = None
        log.info("%s: %s v%s -> v%s", name, follow.alias, before, key and key[0])
        self._apply_unit(*self._unit_source())
        return True

    def _misfit(self, new: ForceClient) -> str | None:
        """Why `new` cannot take this model's place on the same stream (None if it can)."""
        if new.angle_deg != self.angle_deg or new.targets != self.targets:
            return (
                f"it is for {new.angle_deg:g}° and gives {list(new.targets)}, "
                f"this client {self.angle_deg:g}° and {list(self.targets)}"
            )
        # the stream the caller checked, else the one it has been feeding: this model's channels and rate
        channels, rate_hz, rel_tol = self._stream or (self.channels, self.rate_hz, 0.05)
        try:
            new.check_stream(channels, new.rate_hz if rate_hz is None else rate_hz, rel_tol)
        except StreamMismatch as e:
            return str(e)
        return None

    def reset(self, poll: bool = True) -> None:
        """Start a new insertion: forget the window's history and the cue state. A client made by
        `from_registry` first polls its alias if `poll_s` has passed (see `refresh`): a new version is
        swapped in here, never mid-insertion. `poll=False` skips that poll (a caller whose insertion has
        already begun, and that polled when the last one ended)."""
        follow = self._follow
        if poll and follow is not None and _monotonic() >= follow.next_poll:
            self.refresh()
        self._frames = 0
        self._last_t = math.nan
        self._features.reset()
        if self._tracker is not None:
            self._tracker.reset()

    def step(self, volts: Sequence[float] | np.ndarray, t_s: float | None = None) -> Frame:
        """One estimator sample (volts in `channels` order) -> the force now and the cue.

        `t_s` defaults to the previous sample's time plus 1 / rate_hz (0 for the first)."""
        if len(volts) != self._n:
            raise ValueError(f"step takes {self._n} volts ({', '.join(self.channels)}), got {len(volts)}")
        sample = np.asarray(volts, dtype=np.float64)
        if not np.isfinite(sample).all():
            raise ValueError(f"non-finite volts {list(sample)} for channels {list(self.channels)}")
        if t_s is None:
            t_s = 0.0 if self._frames == 0 else self._last_t + 1.0 / (self.rate_hz or 1.0)
        inputs = self._features.push(float(t_s), sample)
        if self._transform is not None:
            inputs = self._transform.apply(inputs)
        x = self._x[0]
        if self.window > 1 and self._frames > 0:
            x[:-1] = x[1:]  # slide the window by one sample (numpy handles the overlap)
            x[-1] = inputs
        else:
            x[...] = inputs  # first sample of an insertion fills the window, as training padded it
        force = self._session.run(self._outputs, self._feed)[0][0].astype(np.float64)
        self._frames += 1
        self._last_t = float(t_s)
        cue = self._tracker.update(self._last_t, sample, force) if self._cues_on else None
        return Frame(self._last_t, force, cue)


def _given_calibration(
    calibration: Path | str | Mapping[str, Any] | None,
) -> tuple[dict[str, Any] | None, dict[str, Any] | None]:
    """(document, where it came from) of a calibration given to `from_dir`: a calibration.json path
    (read and checked) or the document itself."""
    if calibration is None:
        return None, None
    if isinstance(calibration, Mapping):
        doc = dict(calibration)
        if doc.get("format") != UNIT_FORMAT or not doc.get("unit_id"):
            raise ValueError(f"not a {UNIT_FORMAT} calibration document (format {doc.get('format')!r})")
        return doc, {"unit_id": doc["unit_id"]}
    path = Path(calibration)
    doc = read_unit(path)
    info = {"unit_id": doc.get("unit_id"), "path": str(path), "calibration_sha256": file_sha256([path])}
    return doc, info


def _about(info: Mapping[str, Any] | None) -> str:
    """`needle-unit-est-101 v2`, or the file, of a calibration's version info."""
    if not info:
        return "a calibration given"
    if info.get("name"):
        return f"{info['name']} v{info.get('version')}"
    return str(info.get("path") or f"a calibration of {info.get('unit_id')}")
