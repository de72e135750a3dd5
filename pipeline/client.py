"""The needle-insertion simulator's client: fetch an angle's registered force model, run it live.

    client = ForceClient.from_registry(30)          # models:/needle-force-30@champion, cached locally
    client.check_stream(["fsr1", "fsr2", "fsr3"], 30.0)
    client.reset()                                  # at the start of every insertion
    frame = client.step([0.61, 0.58, 0.70], t_s=0.0)  # one 30 Hz sample -> Frame(t_s, force_n, cue)

`fetch` keeps one copy per (model, alias) under the cache folder and falls back to it, with a warning,
when the registry cannot be reached, so a simulator keeps working offline. A client made by
`from_registry` follows its alias: `reset()` asks the registry where the alias points at most once every
`poll_s` seconds and, if it moved, swaps in the new version between insertions (`refresh()` does it on
demand); `step()` never talks to the registry.

The model is the ONNX graph of `pipeline.export` run by onnxruntime; nothing is unpickled. mlflow,
onnxruntime and the cue tracker are imported inside the functions that need them.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import shutil
import tempfile
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd
import yaml

from pipeline import registry
from pipeline.export import DEPLOY_FORMAT
from pipeline.models import TARGETS, file_sha256

if TYPE_CHECKING:
    from pipeline.cues import CueState

log = logging.getLogger(__name__)

DEFAULT_CACHE = Path("~/.cache/needlecue/models").expanduser()
CACHE_ENV = "NEEDLECUE_MODEL_CACHE"
VERSION_FILE = "version.json"
DEFAULT_POLL_S = 60.0
# A poll is one metadata request that must not hold up an insertion's start: against an HTTP registry it
# gets a short timeout and no retries (a failed poll is simply tried again at the next interval).
_POLL_HTTP_ENV = {"MLFLOW_HTTP_REQUEST_TIMEOUT": "2", "MLFLOW_HTTP_REQUEST_MAX_RETRIES": "0"}


class StreamMismatch(ValueError):
    """The estimator stream's channels or rate are not those the model was trained on."""


class ModelNotFound(LookupError):
    """The registry answered, but holds no model version under that name and alias."""


def default_cache_dir() -> Path:
    """`$NEEDLECUE_MODEL_CACHE` if set, else `~/.cache/needlecue/models` (read at call time)."""
    env = os.environ.get(CACHE_ENV)
    return Path(env).expanduser() if env else DEFAULT_CACHE


def _read_version(folder: Path) -> dict[str, Any] | None:
    """The folder's version.json, or None if it is missing or unreadable (then it is no usable copy)."""
    try:
        info = json.loads((folder / VERSION_FILE).read_text())
    except (OSError, ValueError):
        return None
    return info if isinstance(info, dict) else None


def _read_metadata(model_dir: Path) -> dict[str, Any]:
    """The `needlecue` block of a model folder's MLmodel (plain YAML: no mlflow import, no pickle)."""
    mlmodel = model_dir / "MLmodel"
    if not mlmodel.is_file():
        raise FileNotFoundError(f"{model_dir} is not a fetched model folder: it has no MLmodel file")
    try:
        spec = yaml.safe_load(mlmodel.read_text()) or {}
    except yaml.YAMLError as e:
        raise ValueError(f"{mlmodel}: not valid YAML: {e}") from e
    meta = (spec.get("metadata") or {}).get("needlecue")
    if not isinstance(meta, dict) or meta.get("format") != DEPLOY_FORMAT:
        found = meta.get("format") if isinstance(meta, dict) else None
        raise ValueError(
            f"{mlmodel}: no {DEPLOY_FORMAT} block under metadata.needlecue (found format {found!r}); "
            "was this model logged with pipeline.export.log_onnx_model?"
        )
    return meta


@contextlib.contextmanager
def _env(values: dict[str, str]) -> Iterator[None]:
    """Set environment variables for the block; each restored (or removed) after it."""
    before = {key: os.environ.get(key) for key in values}
    os.environ.update(values)
    try:
        yield
    finally:
        for key, value in before.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value


def _quiet_downloads() -> contextlib.AbstractContextManager[None]:
    """No tqdm progress bar per download (it would spam a simulator's console); env restored after."""
    return _env({"MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR": "false"})


def _monotonic() -> float:
    """The clock of the alias polls (a function of its own, so that tests can move it)."""
    return time.monotonic()


def fetch(
    angle_deg: float,
    alias: str = registry.CHAMPION,
    *,
    cache_dir: Path | None = None,
    tracking_uri: str | None = None,
) -> Path:
    """The local folder of `models:/needle-force-<angle>@<alias>`: `<cache_dir>/needle-force-<angle>/<alias>/`
    (MLmodel, model.onnx, version.json), downloaded unless the cached copy is already that version.

    Unreachable registry: the cached copy is used with a warning, or `RegistryUnreachable` is raised
    naming the URI and the cache path if there is none. `ModelNotFound` if the registry has no such
    alias. `cache_dir` defaults to `default_cache_dir()`.
    """
    name = registry.model_name(angle_deg)
    uri = registry.model_uri(angle_deg, alias)
    target = Path(cache_dir or default_cache_dir()).expanduser() / name / alias
    store = tracking_uri or registry.tracking_uri()
    cached = _read_version(target)
    try:
        client = registry.connect(store, must_exist=True)
        mv = _resolve(client, name, alias, store)
    except registry.RegistryUnreachable as e:
        return _offline_copy(target, cached, uri, e)

    if (
        cached is not None
        and cached.get("name") == name
        and str(cached.get("version")) == str(mv.version)
        # version numbers restart in every store: the source (models:/m-<id>) tells two stores' "v1" apart
        and cached.get("source") == mv.source
        and (target / "model.onnx").is_file()
        and file_sha256([target / "model.onnx"]) == cached.get("onnx_sha256")
    ):
        return target  # already that version, intact: no download
    try:
        return _download(mv, alias, target, store)
    except (OSError, registry.RegistryUnreachable) as e:  # the connection dropped mid-download
        return _offline_copy(target, cached, uri, e)


def _resolve(client: Any, name: str, alias: str, store: str) -> Any:
    """The ModelVersion behind `name@alias`; `ModelNotFound` if the registry has none."""
    from mlflow.exceptions import MlflowException

    try:
        return client.get_model_version_by_alias(name, alias)
    except MlflowException as e:
        if e.error_code in ("RESOURCE_DOES_NOT_EXIST", "INVALID_PARAMETER_VALUE"):
            raise ModelNotFound(
                f"the registry at {store} has no version of {name!r} with the alias {alias!r} "
                f"({str(e).splitlines()[0][:200]}); run `make repro` to train and register the models"
            ) from e
        raise registry.RegistryUnreachable(
            f"registry at {store} failed to resolve {name}@{alias}: {e}"
        ) from e
    except Exception as e:  # e.g. a connection dropped after connect() succeeded
        raise registry.RegistryUnreachable(f"registry at {store}: {type(e).__name__}: {e}") from e


def _offline_copy(target: Path, cached: dict[str, Any] | None, uri: str, error: Exception) -> Path:
    """The cached copy, with a warning, when the registry cannot be used; else a clear error."""
    if cached is None:
        raise registry.RegistryUnreachable(
            f"cannot fetch {uri}: {error}; and there is no local copy at {target}"
        ) from error
    log.warning(
        "offline: %s; using the local copy of %s (version %s, fetched %s) at %s",
        error,
        uri,
        cached.get("version"),
        cached.get("fetched_utc"),
        target,
    )
    return target


def _download(mv: Any, alias: str, target: Path, store: str) -> Path:
    """Download a model version into a temp sibling of `target`, then swap it in (never a partial copy)."""
    import mlflow
    from mlflow.exceptions import MlflowException

    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{alias}-download-", dir=target.parent))
    tmp.chmod(0o755)  # mkdtemp's 0700 would hide a shared cache's copy from other users
    try:
        with _quiet_downloads():
            # by version, not alias: the alias may move between resolving it and downloading
            try:
                mlflow.artifacts.download_artifacts(
                    artifact_uri=f"models:/{mv.name}/{mv.version}", dst_path=str(tmp), tracking_uri=store
                )
            except MlflowException as e:
                raise registry.RegistryUnreachable(
                    f"downloading {mv.name} version {mv.version} from {store} failed: {e}"
                ) from e
        missing = [f for f in ("MLmodel", "model.onnx") if not (tmp / f).is_file()]
        if missing:  # a broken registered model is an error, not a reason to go offline
            raise ValueError(f"{mv.name} version {mv.version} ({mv.source}) has no {' or '.join(missing)}")
        meta = _read_metadata(tmp)
        info = {
            "name": mv.name,
            "version": str(mv.version),
            "alias": alias,
            "run_id": mv.run_id,
            "source": mv.source,
            "checkpoint_sha256": meta.get("checkpoint_sha256"),
            "onnx_sha256": file_sha256([tmp / "model.onnx"]),
            "tracking_uri": store,
            "fetched_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        }
        (tmp / VERSION_FILE).write_text(json.dumps(info, indent=2) + "\n")
        _swap_in(tmp, target)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return target


def _swap_in(new: Path, target: Path) -> None:
    """Replace folder `target` by `new` with renames (atomic per rename; a reader sees old or new)."""
    old = None
    if target.exists():
        old = Path(tempfile.mkdtemp(prefix=f".{target.name}-old-", dir=target.parent))
        os.replace(target, old / "copy")
    try:
        os.replace(new, target)
    except OSError:
        # another process swapped in its own download meanwhile: keep theirs, it is as fresh as ours
        if _read_version(target) is None:
            if old is not None and not target.exists():
                os.replace(old / "copy", target)  # put the previous copy back rather than none
            raise
        shutil.rmtree(new, ignore_errors=True)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


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
        self.metadata: dict[str, Any] = _read_metadata(self.model_dir)
        meta = self.metadata
        self.kind: str = meta["kind"]
        self.angle_deg: float = float(meta["angle_deg"])
        self.channels: tuple[str, ...] = tuple(meta["channels"])
        self.targets: tuple[str, ...] = tuple(meta["targets"])
        self.rate_hz: float | None = None if meta.get("rate_hz") is None else float(meta["rate_hz"])
        self.window: int = int(meta["window"])
        self.version: dict[str, Any] | None = _read_version(self.model_dir)
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
            from pipeline.cues import CueTracker

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
        alias: str = registry.CHAMPION,
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
        kwargs["tracking_uri"] = kwargs.get("tracking_uri") or registry.tracking_uri()
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
        name = registry.model_name(follow.angle_deg)
        store = follow.fetch_kwargs["tracking_uri"]
        try:
            with _env(_POLL_HTTP_ENV):  # one quick metadata request: no retries, short timeout
                mv = _resolve(registry.connect(store, must_exist=True), name, follow.alias, store)
        except (registry.RegistryUnreachable, ModelNotFound) as e:
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
            registry.model_name(follow.angle_deg),
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
        name = registry.model_name(follow.angle_deg)
        before = (self.version or {}).get("version")
        try:
            new = type(self)(fetch(follow.angle_deg, follow.alias, **follow.fetch_kwargs))
        except (registry.RegistryUnreachable, ModelNotFound) as e:
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


def stream_rate_hz(t_s: np.ndarray) -> float:
    """A recording's sample rate: 1 / the median positive time step (nan if there are fewer than 2)."""
    dt = np.diff(np.sort(np.asarray(t_s, dtype=np.float64)))
    dt = dt[dt > 0]
    return float(1.0 / np.median(dt)) if len(dt) else math.nan


def replay(frame: pd.DataFrame, client: ForceClient) -> pd.DataFrame:
    """Run one recorded trial through `client.step`, sample by sample as if live (after a reset).

    Returns one row per sample in t_s order: t_s, the predicted fx, fy, fz, the reference fx_ref,
    fy_ref, fz_ref if the frame has them, cue, angle_est_deg and reason (None without cues).
    """
    missing = [c for c in (*client.channels, "t_s") if c not in frame.columns]
    if missing:
        raise StreamMismatch(
            f"the recording lacks column(s) {missing}: {client.name} reads {list(client.channels)} "
            f"and t_s; the recording has {list(frame.columns)}"
        )
    keys = [c for c in ("batch_id", "trial_id") if c in frame.columns]
    if keys and len(trials := frame[keys].drop_duplicates()) > 1:
        raise ValueError(f"replay takes one trial at a time, got {len(trials)} ({keys})")
    rows = frame.sort_values("t_s", kind="stable")
    volts = rows[list(client.channels)].to_numpy(np.float64)
    t = rows["t_s"].to_numpy(np.float64)
    force = np.empty((len(rows), len(client.targets)))
    cues: list[str | None] = []
    angles: list[float | None] = []
    reasons: list[str | None] = []
    client.reset()
    for i in range(len(rows)):
        out = client.step(volts[i], float(t[i]))
        force[i] = out.force_n
        cues.append(None if out.cue is None else out.cue.cue)
        angles.append(None if out.cue is None else out.cue.angle_est_deg)
        reasons.append(None if out.cue is None else out.cue.reason)
    result = pd.DataFrame({"t_s": t, **{c: force[:, i] for i, c in enumerate(client.targets)}})
    for c in TARGETS:
        if c in rows.columns:
            result[f"{c}_ref"] = rows[c].to_numpy(np.float64)
    result["cue"] = pd.Series(cues, dtype=object)
    result["angle_est_deg"] = pd.Series(angles, dtype="float64")
    result["reason"] = pd.Series(reasons, dtype=object)
    return result


def cue_changes(replayed: pd.DataFrame) -> pd.DataFrame:
    """The rows of a `replay` result where the cue changes (the first row included): the timeline."""
    if replayed.empty or replayed["cue"].isna().all():
        return replayed.iloc[:0]
    cue = replayed["cue"].astype(object)
    return replayed[cue.ne(cue.shift())]


def rmse(replayed: pd.DataFrame) -> dict[str, float]:
    """RMSE in N per axis of a `replay` result against its reference (empty if it has none)."""
    return {
        c: float(np.sqrt(np.mean((replayed[c] - replayed[f"{c}_ref"]) ** 2)))
        for c in TARGETS
        if f"{c}_ref" in replayed.columns and c in replayed.columns
    }


CUE_COLOURS = {"wait": "#bbbbbb", "continue": "#7fc97f", "correct": "#fdb462", "stop": "#e7298a"}


def plot_replay(replayed: pd.DataFrame, out: Path, title: str) -> Path:
    """A PNG of predicted vs reference fx, fy, fz over time, the cue intervals shaded (Agg, no pyplot)."""
    from matplotlib.figure import Figure
    from matplotlib.patches import Patch

    fig = Figure(figsize=(10, 7), layout="constrained")
    axes = fig.subplots(3, 1, sharex=True)
    t = replayed["t_s"].to_numpy()
    changes = cue_changes(replayed)
    starts = changes["t_s"].tolist()
    ends = [*starts[1:], float(t[-1])] if starts else []
    spans = list(zip(starts, ends, changes["cue"].tolist(), strict=True))
    for ax, c in zip(axes, TARGETS, strict=True):
        for lo, hi, cue in spans:
            ax.axvspan(lo, hi, color=CUE_COLOURS.get(cue, "#dddddd"), alpha=0.25, linewidth=0)
        if f"{c}_ref" in replayed.columns:
            ax.plot(t, replayed[f"{c}_ref"], color="black", linewidth=1.0, label="reference")
        ax.plot(t, replayed[c], color="tab:blue", linewidth=1.0, label="predicted")
        ax.set_ylabel(f"{c} (N)")
        ax.grid(alpha=0.3)
    handles, labels = axes[0].get_legend_handles_labels()
    seen = list(dict.fromkeys(cue for _, _, cue in spans))
    handles += [Patch(color=CUE_COLOURS.get(cue, "#dddddd"), alpha=0.4) for cue in seen]
    labels += [f"cue: {cue}" for cue in seen]
    axes[0].legend(handles, labels, loc="upper right", fontsize=8, ncols=2)
    axes[-1].set_xlabel("t (s)")
    fig.suptitle(title)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    return out
