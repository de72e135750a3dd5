"""The simulator's live force model: `ForceClient` runs one fetched model sample by sample.

A client reads a model folder (the `needlecue` block of its MLmodel and its model.onnx) and runs the
ONNX graph with onnxruntime, one frame at a time on pre-allocated arrays, with the cue tracker beside
it when the model carries a cue pack; nothing is unpickled. A client made by `from_registry` follows
its alias: `reset()` asks the registry where the alias points at most once every `poll_s` seconds and,
if it moved, swaps in the new version between insertions (`refresh()` does it on demand); `step()`
never talks to the registry. onnxruntime and the cue tracker are imported inside the functions that
need them.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from pipeline.client.cache import (
    ModelNotFound,
    default_cache_dir,
    fetch,
    poll_alias,
    read_metadata,
    read_version,
)
from pipeline.registry import store

if TYPE_CHECKING:
    from pipeline.cues.tracker import CueState

# One logger for the whole client, named as before it was split into modules (log configs keep working).
log = logging.getLogger("pipeline.client")

DEFAULT_POLL_S = 60.0


class StreamMismatch(ValueError):
    """The estimator stream's channels or rate are not those the model was trained on."""


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
    """

    def __init__(self, model_dir: Path) -> None:
        import onnxruntime as ort

        self._follow: _Follow | None = None  # set by from_registry
        self._stream: tuple[tuple[str, ...], float, float] | None = None  # the last stream checked
        self.model_dir = Path(model_dir)
        self.metadata: dict[str, Any] = read_metadata(self.model_dir)
        meta = self.metadata
        self.kind: str = meta["kind"]
        self.angle_deg: float = float(meta["angle_deg"])
        self.channels: tuple[str, ...] = tuple(meta["channels"])
        self.targets: tuple[str, ...] = tuple(meta["targets"])
        self.rate_hz: float | None = None if meta.get("rate_hz") is None else float(meta["rate_hz"])
        self.window: int = int(meta["window"])
        self.version: dict[str, Any] | None = read_version(self.model_dir)
        onnx_file = self.model_dir / "model.onnx"
        if not onnx_file.is_file():
            raise FileNotFoundError(f"{self.model_dir} has no model.onnx")

        opts = ort.SessionOptions()
        # one frame at a time: threads would only add hand-off latency (and share the simulator's cores)
        opts.intra_op_num_threads = 1
        opts.inter_op_num_threads = 1
        opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        self._session = ort.InferenceSession(str(onnx_file), opts, providers=["CPUExecutionProvider"])
        inputs, outputs = self._session.get_inputs(), self._session.get_outputs()
        shape = (self.window, len(self.channels)) if self.kind == "lstm" else (len(self.channels),)
        if [i.name for i in inputs] != [meta["input"]] or tuple(inputs[0].shape[1:]) != shape:
            found = [(i.name, i.shape) for i in inputs]
            raise ValueError(
                f"{onnx_file}: inputs {found} do not match its MLmodel metadata "
                f"({meta['input']!r} of shape (batch, {', '.join(map(str, shape))}))"
            )
        # Pre-allocated per-frame state: `step` writes into these arrays instead of allocating.
        self._x = np.zeros((1, *shape), dtype=np.float32)
        self._feed = {meta["input"]: self._x}
        self._outputs = [outputs[0].name]
        self._n = len(self.channels)
        self._tracker: Any = None
        pack = meta.get("cues")
        if pack is not None:
            from pipeline.cues.tracker import CueTracker

            if list(pack.get("channels", self.channels)) != list(self.channels):
                raise ValueError(
                    f"{self.model_dir}: the cue pack reads channels {pack.get('channels')}, "
                    f"the model {list(self.channels)}"
                )
            # the paper-method thresholds were calibrated per model kind: use this model's if there
            kinds = (pack.get("thresholds") or {}).get("profile") or {}
            self._tracker = CueTracker(
                pack, self.angle_deg, model_kind=self.kind if self.kind in kinds else None
            )
        self.reset()

    @classmethod
    def from_dir(cls, model_dir: Path) -> ForceClient:
        """The client of a fetched model folder (MLmodel + model.onnx)."""
        return cls(Path(model_dir))

    @classmethod
    def from_registry(
        cls,
        angle_deg: float,
        alias: str = store.CHAMPION,
        *,
        poll_s: float | None = DEFAULT_POLL_S,
        **fetch_kwargs: Any,
    ) -> ForceClient:
        """Fetch (or reuse the cached) `models:/needle-force-<angle>@<alias>` and load it.

        The client follows the alias: `reset()` asks the registry where it points at most once every
        `poll_s` seconds (None or 0: never by itself; `refresh(force=True)` still does) and swaps in a
        new version (see `refresh`). It polls and fetches from the store and cache of this first fetch
        (`tracking_uri`, `cache_dir`: the defaults are read now).
        """
        if poll_s is not None and not poll_s >= 0:
            raise ValueError(f"poll_s is seconds >= 0 or None, got {poll_s!r}")
        kwargs = dict(fetch_kwargs)
        kwargs["tracking_uri"] = kwargs.get("tracking_uri") or store.tracking_uri()
        kwargs["cache_dir"] = Path(kwargs.get("cache_dir") or default_cache_dir()).expanduser()
        client = cls(fetch(angle_deg, alias, **kwargs))
        client._follow = _Follow(
            angle_deg, alias, kwargs, poll_s or None, _monotonic() + poll_s if poll_s else math.inf
        )
        return client

    @property
    def name(self) -> str:
        """`needle-force-30 v3 (lstm)`, or the folder for an unregistered copy."""
        if self.version:
            return f"{self.version.get('name')} v{self.version.get('version')} ({self.kind})"
        return f"{self.model_dir} ({self.kind})"

    @property
    def has_cues(self) -> bool:
        return self._tracker is not None

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
        in; True if a new model was loaded (`version`, `kind`, `window`, ... are then the new one's).

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
            return False
        return self._swap(found)

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
            new = type(self)(fetch(follow.angle_deg, follow.alias, **follow.fetch_kwargs))
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
            return False
        problem = self._misfit(new)
        if problem is not None:
            follow.refused = key
            log.error(
                "%s: %s v%s refused, keeping v%s: %s", name, follow.alias, key and key[0], before, problem
            )
            return False
        keep = {"_follow": follow, "_stream": self._stream}
        vars(self).update(vars(new))
        vars(self).update(keep)
        follow.refused = None
        log.info("%s: %s v%s -> v%s", name, follow.alias, before, key and key[0])
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

    def reset(self) -> None:
        """Start a new insertion: forget the window's history and the cue state. A client made by
        `from_registry` first polls its alias if `poll_s` has passed (see `refresh`): a new version is
        swapped in here, never mid-insertion."""
        follow = self._follow
        if follow is not None and _monotonic() >= follow.next_poll:
            self.refresh()
        self._frames = 0
        self._last_t = math.nan
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
        x = self._x[0]
        if self.window > 1 and self._frames > 0:
            x[:-1] = x[1:]  # slide the window by one sample (numpy handles the overlap)
            x[-1] = sample
        else:
            x[...] = sample  # first sample of an insertion fills the window, as training padded it
        force = self._session.run(self._outputs, self._feed)[0][0].astype(np.float64)
        self._frames += 1
        self._last_t = float(t_s)
        cue = None if self._tracker is None else self._tracker.update(self._last_t, sample, force)
        return Frame(self._last_t, force, cue)
