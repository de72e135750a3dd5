"""Fetching a registered force model, and an estimator unit's calibration, into the simulator's local
cache.

`fetch` resolves `models:/needle-force-<angle>@<alias>` in the registry and keeps one copy per (model,
alias) under the cache folder: `<cache>/needle-force-<angle>/<alias>/` holding MLmodel, model.onnx and
version.json (what was fetched, from where and when). A copy is downloaded only when the alias points
elsewhere, into a temp sibling swapped in by renames, so a reader never sees half a model. When the
registry cannot be reached the cached copy is used with a warning, so a simulator keeps working
offline. `poll_alias` is the quick "where does the alias point now" request of a client that follows
its alias. `fetch_unit` does the same for `models:/needle-unit-<unit_id>@current`, a unit's calibration
document: `<cache>/needle-unit-<unit_id>/<alias>/` holding calibration.json and version.json. mlflow is
imported inside the functions that talk to the registry.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import shutil
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pipeline.client.published as published
from pipeline.calibration.document import FILE as UNIT_FILE
from pipeline.calibration.document import read_unit
from pipeline.client.folder import MLMODEL, ONNX_FILE, open_model
from pipeline.registry import store
from pipeline.vocab import file_sha256

# One logger for the whole client, named as before it was split into modules (log configs keep working).
log = logging.getLogger("pipeline.client")

DEFAULT_CACHE = Path("~/.cache/needlecue/models").expanduser()
CACHE_ENV = "NEEDLECUE_MODEL_CACHE"
VERSION_FILE = "version.json"
# What a simulator runs of a force model: its description and its ONNX (not the environment files)
MODEL_FILES = (MLMODEL, ONNX_FILE)
# A poll is one metadata request that must not hold up an insertion's start: against an HTTP registry it
# gets a short timeout and no retries (a failed poll is simply tried again at the next interval).
_POLL_HTTP_ENV = {"MLFLOW_HTTP_REQUEST_TIMEOUT": "2", "MLFLOW_HTTP_REQUEST_MAX_RETRIES": "0"}
MODEL_HINT = "run `make repro` to train and register the models"
UNIT_PREFIX = "needle-unit-"  # store.unit_model_name's
UNIT_HINT = "record a calibration batch with that unit and run `needlecue calibrate BATCH_DIR`"


class ModelNotFound(LookupError):
    """The registry answered, but holds no model version under that name and alias."""


class CachedCopyRefused(store.RegistryUnreachable):
    """The registry cannot be used and the local copy fails its check (changed, damaged, or another
    model's): it is not run."""


def default_cache_dir() -> Path:
    """`$NEEDLECUE_MODEL_CACHE` if set, else `~/.cache/needlecue/models` (read at call time)."""
    env = os.environ.get(CACHE_ENV)
    return Path(env).expanduser() if env else DEFAULT_CACHE


def source_uri(tracking_uri: str | None = None) -> str:
    """Where a client fetches from: `tracking_uri` if given, else the published bucket of
    `$NEEDLECUE_PUBLISHED_URL` if set, else MLflow's tracking URI (read at call time)."""
    return tracking_uri or published.default_location() or store.tracking_uri()


def read_version(folder: Path) -> dict[str, Any] | None:
    """The folder's version.json, or None if it is missing or unreadable (then it is no usable copy)."""
    try:
        info = json.loads((folder / VERSION_FILE).read_text())
    except (OSError, ValueError):
        return None
    return info if isinstance(info, dict) else None


def _quiet_downloads() -> contextlib.AbstractContextManager[None]:
    """No tqdm progress bar per download (it would spam a simulator's console); env restored after."""
    return store.environment({"MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR": "false"})


def fetch(
    angle_deg: float,
    alias: str = store.CHAMPION,
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
    name = store.model_name(angle_deg)
    return _fetch_version(
        name,
        alias,
        cache_dir,
        tracking_uri,
        ONNX_FILE,
        "onnx_sha256",
        MODEL_HINT,
        _model_info,
        _model_problem(name, angle_deg),
        only=MODEL_FILES,
    )


def poll_alias(name: str, alias: str, tracking_uri: str | None) -> Any:
    """The ModelVersion `name@alias` points to now, asked quickly (short timeout, no retries over HTTP).
    `RegistryUnreachable` or `ModelNotFound` as for `fetch`.

    A server is asked in one request, without `store.connect`'s check (one more request per poll,
    for every simulator): the client that polls fetched from it already, and whatever the answer names
    is fetched, with those checks, before it runs. No answer, or a server error (5xx), is unreachable
    at once: more requests would only load a busy server. A 4xx, or an answer that is not a version,
    takes the full way, which says what is wrong (no such model or alias, credentials, not MLflow)."""
    from mlflow import MlflowClient
    from mlflow.exceptions import MlflowException

    hint = UNIT_HINT if name.startswith(UNIT_PREFIX) else MODEL_HINT
    uri = source_uri(tracking_uri)
    if published.is_published(uri):
        found, _ = _published_manifest(uri, name, alias, hint)
        return _Version(found)
    with store.environment(_POLL_HTTP_ENV):
        if uri.startswith(("http://", "https://")):
            try:
                mv = MlflowClient(tracking_uri=uri, registry_uri=uri).get_model_version_by_alias(name, alias)
            except MlflowException as e:
                # MLflow reports a timeout or a refused connection as an internal error (500) too
                if e.get_http_status_code() >= 500:
                    raise store.RegistryUnreachable(f"registry at {uri}: {e.message}") from e
                mv = None  # no such model or alias (403 with workspaces on), a login, not MLflow: below
            except Exception as e:  # anything MLflow did not wrap
                raise store.RegistryUnreachable(f"registry at {uri}: {type(e).__name__}: {e}") from e
            if mv is not None and mv.version and mv.source:
                return mv
        return _resolve(store.connect(uri, must_exist=True), name, alias, uri, hint)


def fetch_unit(
    unit_id: str,
    alias: str = store.UNIT_ALIAS,
    *,
    cache_dir: Path | None = None,
    tracking_uri: str | None = None,
) -> Path:
    """The local folder of `models:/needle-unit-<unit_id>@<alias>`, the unit's calibration document:
    `<cache_dir>/needle-unit-<unit_id>/<alias>/` (calibration.json, version.json), downloaded unless
    the cached copy is already that version.

    As `fetch`: an unreachable registry falls back to the cached copy with a warning (else
    `RegistryUnreachable`); `ModelNotFound` if the unit has no calibration registered under `alias`.
    """
    name = store.unit_model_name(unit_id)
    return _fetch_version(
        name,
        alias,
        cache_dir,
        tracking_uri,
        UNIT_FILE,
        "calibration_sha256",
        UNIT_HINT,
        _unit_info(unit_id),
        _unit_problem(name, unit_id),
        offline_needs_file=True,
    )


def _fetch_version(
    name: str,
    alias: str,
    cache_dir: Path | None,
    tracking_uri: str | None,
    file: str,
    sha_key: str,
    hint: str,
    describe: Describe,
    problem: Verify,
    *,
    offline_needs_file: bool = False,
    only: tuple[str, ...] | None = None,
) -> Path:
    """`fetch` and `fetch_unit`: `<cache_dir>/<name>/<alias>/`, downloaded (and described) unless the
    cached copy is that very version with `file` intact (its sha256 under `sha_key` in version.json);
    the cached copy when the registry cannot be used (a unit's only if its `file` is there), once
    `problem(folder, version.json)` finds nothing wrong with it. `only`: download just these files of
    the version (default: all of it)."""
    uri = f"models:/{name}@{alias}"
    target = Path(cache_dir or default_cache_dir()).expanduser() / name / alias
    registry_uri = source_uri(tracking_uri)
    cached = read_version(target) if not offline_needs_file or (target / file).is_file() else None
    if published.is_published(registry_uri):
        light = _signed_model_fields if describe is _model_info else describe  # parsed once, to run it
        return _fetch_published(
            name, alias, target, cached, registry_uri, (file, sha_key), hint, light, problem
        )
    try:
        with store.patience():
            mv = _resolve(store.connect(registry_uri, must_exist=True), name, alias, registry_uri, hint)
    except store.RegistryUnreachable as e:
        return _offline_copy(target, cached, uri, e, problem)
    if (
        cached is not None
        and cached.get("name") == name
        and _is_copy_of(cached, mv.version, mv.source, target, file, sha_key)
    ):
        return target  # already that version, intact: no download
    try:
        with store.patience():
            return _download(mv, alias, target, registry_uri, describe, only)
    except (OSError, store.RegistryUnreachable) as e:  # the connection dropped mid-download
        return _offline_copy(target, cached, uri, e, problem)


def _is_copy_of(
    cached: dict[str, Any] | None, version: Any, source: Any, target: Path, file: str, sha_key: str
) -> bool:
    """Whether the cached copy is that very version with `file` intact (version numbers restart in every
    store: the source, models:/m-<id>, tells two stores' "v1" apart)."""
    return (
        cached is not None
        and str(cached.get("version")) == str(version)
        and cached.get("source") == source
        and (target / file).is_file()
        and file_sha256([target / file]) == cached.get(sha_key)
    )


class _Version:
    """What a client reads of a model version (as MLflow's ModelVersion), from a verified manifest."""

    def __init__(self, manifest: dict[str, Any]) -> None:
        self.name, self.version, self.source = manifest["name"], str(manifest["version"]), manifest["source"]
        self.run_id = manifest.get("run_id")
        self.describe = manifest.get("describe") or {}
        sha = self.describe.get("calibration_sha256")
        self.tags = {store.CALIBRATION_SHA_TAG: sha} if sha else {}


def _published_manifest(uri: str, name: str, alias: str, hint: str) -> tuple[dict[str, Any], bytes | None]:
    """The verified manifest of `name@alias` in the published bucket, and its signed bytes (None when
    the poll was answered 304); `ModelNotFound` if nothing is published under it."""
    bucket = published.bucket(uri)
    found = bucket.manifest(name, alias)
    if found is None:
        raise ModelNotFound(
            f"the published bucket {bucket.where} has no {name}@{alias}; {hint}, and have the lab publish "
            "it (`needlecue team publish`)"
        )
    return found[0], found[1]


MANIFEST_FILE = "manifest.json"  # a published copy's signed manifest, kept beside its files


def _fetch_published(
    name: str,
    alias: str,
    target: Path,
    cached: dict[str, Any] | None,
    uri: str,
    file_key: tuple[str, str],
    hint: str,
    describe: Describe,
    problem: Verify,
) -> Path:
    """`_fetch_version` from a published bucket: the manifest by conditional GET (its cached copy's ETag
    first), the files by hash, everything verified before it is written; the checked cached copy when
    the bucket cannot be used or refuses what it holds."""
    file, sha_key = file_key
    bucket = published.bucket(uri)
    known = bucket.etag(name, alias) is not None
    if not known and cached and cached.get("manifest_etag") and (target / MANIFEST_FILE).is_file():
        with contextlib.suppress(ValueError, OSError):  # an unreadable one is simply fetched again
            bucket.remember(name, alias, cached["manifest_etag"], (target / MANIFEST_FILE).read_bytes())
    try:
        found, document = _published_manifest(uri, name, alias, hint)
        if _is_copy_of(cached, found["version"], found["source"], target, file, sha_key):
            return target  # already that version, intact (the client checks the folder as it opens it)
        return _download_published(bucket, found, document, alias, target, describe)
    except store.RegistryUnreachable as e:  # PublishedRefused too: the verified cached copy runs
        return _offline_copy(target, cached, f"{bucket.where} {name}@{alias}", e, problem)


def _download_published(
    bucket: published.Bucket,
    found: dict[str, Any],
    document: bytes | None,
    alias: str,
    target: Path,
    describe: Describe,
) -> Path:
    """The manifest's files, each checked against its hash, into a temp sibling of `target`, described
    and swapped in as `_download` does."""
    if document is None:  # answered 304 for a manifest whose cached files are gone: fetch it whole
        bucket.forget(found["name"], alias)
        found, document = _published_manifest(bucket.uri, found["name"], alias, "")
        assert document is not None
    with _staging(target, alias) as tmp:
        for fname, entry in sorted(found["files"].items()):
            if fname in ("", ".", "..", VERSION_FILE, MANIFEST_FILE) or "/" in fname or "\\" in fname:
                raise published.PublishedRefused(
                    f"{bucket.where}: refused, the manifest names a file {fname!r}"
                )
            (tmp / fname).write_bytes(bucket.object(entry))
        mv = _Version(found)
        try:
            described = describe(tmp, mv)
        except ValueError as e:  # signed, but not a version a simulator may run
            raise published.PublishedRefused(f"{bucket.where} {mv.name} v{mv.version}: {e}") from e
        if any(found["describe"].get(k) != v for k, v in described.items()):
            raise published.PublishedRefused(
                f"{bucket.where} {mv.name} v{mv.version}: refused, its files are not what the manifest says"
            )
        (tmp / MANIFEST_FILE).write_bytes(document)
        extra = {"published_utc": found["published_utc"], "key_id": found.get("key_id"),
                 "manifest_etag": bucket.etag(found["name"], alias)}  # fmt: skip
        _write_version(tmp, mv, alias, described, bucket.uri, extra)
    return target


def download_checked(mv: Any, alias: str, target: Path, registry_uri: str) -> Path:
    """A model version's files a simulator runs, downloaded from the registry into `target` and checked
    as a client checks them (a broken version raises ValueError): what the lab publishes."""
    if mv.name.startswith(UNIT_PREFIX):
        unit_id = mv.name[len(UNIT_PREFIX) :]
        return _download(mv, alias, target, registry_uri, _unit_info(unit_id), (UNIT_FILE,))
    return _download(mv, alias, target, registry_uri, _model_info, MODEL_FILES)


def _resolve(client: Any, name: str, alias: str, registry_uri: str, hint: str = MODEL_HINT) -> Any:
    """The ModelVersion behind `name@alias`; `ModelNotFound` if the registry has none, and
    `RegistryUnreachable` for any other failure of the registry."""
    from mlflow.exceptions import MlflowException

    try:
        mv = store.alias_version(client, name, alias)
    except MlflowException as e:
        raise store.RegistryUnreachable(
            f"registry at {registry_uri} failed to resolve {name}@{alias}: {e}"
        ) from e
    except Exception as e:  # e.g. a connection dropped after connect() succeeded
        raise store.RegistryUnreachable(f"registry at {registry_uri}: {type(e).__name__}: {e}") from e
    if mv is None:
        raise ModelNotFound(
            f"the registry at {registry_uri} has no version of {name!r} with the alias {alias!r}; {hint}"
        )
    return mv


def _offline_copy(
    target: Path, cached: dict[str, Any] | None, uri: str, error: Exception, problem: Verify
) -> Path:
    """The cached copy, checked, with a warning, when the registry cannot be used; else a clear error
    (`CachedCopyRefused` when the copy fails its check)."""
    if cached is None and (target / VERSION_FILE).is_file():  # a copy is there, but not what it is
        raise CachedCopyRefused(
            f"cannot fetch {uri}: {error}; the local copy at {target} is refused: its {VERSION_FILE} is "
            "unreadable (not a JSON object: damaged?), so what it holds is unknown. Reconnect to the "
            "registry to fetch it again, or delete that folder"
        ) from error
    if cached is None:  # a refusal stays one: the caller learns the copy is not the lab's
        kind = (
            published.PublishedRefused
            if isinstance(error, published.PublishedRefused)
            else store.RegistryUnreachable
        )
        raise kind(f"cannot fetch {uri}: {error}; and there is no local copy at {target}") from error
    if why := problem(target, cached):
        raise CachedCopyRefused(
            f"cannot fetch {uri}: {error}; the local copy at {target} is refused: {why}. Reconnect to "
            "the registry to fetch it again, or delete that folder"
        ) from error
    refused = isinstance(error, published.PublishedRefused)  # not the lab's: said loudly, not run
    log.log(
        logging.ERROR if refused else logging.WARNING,
        "%s: %s; using the verified local copy of %s (version %s, fetched %s) at %s",
        "refused" if refused else "offline",
        error,
        uri,
        cached.get("version"),
        cached.get("fetched_utc"),
        target,
    )
    return target


Describe = Callable[[Path, Any], dict[str, Any]]  # (downloaded folder, ModelVersion) -> version.json fields
Verify = Callable[[Path, dict[str, Any]], str | None]  # (cached folder, its version.json) -> what is wrong


def _copy_problem(folder: Path, info: dict[str, Any], name: str, file: str, sha_key: str) -> str | None:
    """What makes a cached copy of `name` unusable, as far as version.json and `file` tell."""
    if info.get("name") != name:
        return f"its version.json is of {info.get('name')!r}, not {name!r}"
    if not info.get("version"):
        return "its version.json names no version"
    if not (folder / file).is_file():
        return f"it has no {file}"
    if file_sha256([folder / file]) != info.get(sha_key):
        return f"{file} is not the file fetched (its sha256 differs from version.json's): changed or damaged"
    return None


def _model_problem(name: str, angle_deg: float) -> Verify:
    """A cached force model: the copy of `name`, its ONNX as fetched, its MLmodel readable and of that
    angle and checkpoint."""

    def problem(folder: Path, info: dict[str, Any]) -> str | None:
        if why := _copy_problem(folder, info, name, ONNX_FILE, "onnx_sha256"):
            return why
        try:
            meta, _ = open_model(folder)  # the graph and its description, as registered
        except (OSError, ValueError) as e:
            return str(e)
        if float(meta.get("angle_deg", "nan")) != float(angle_deg):
            return f"its MLmodel is of the {meta.get('angle_deg')}° model, not {angle_deg:g}°"
        if meta.get("checkpoint_sha256") != info.get("checkpoint_sha256"):
            return "its MLmodel names another checkpoint than the one fetched"
        return None

    return problem


def _unit_problem(name: str, unit_id: str) -> Verify:
    """A cached unit calibration: the copy of `name`, its document as fetched and of that unit."""

    def problem(folder: Path, info: dict[str, Any]) -> str | None:
        if why := _copy_problem(folder, info, name, UNIT_FILE, "calibration_sha256"):
            return why
        try:
            doc = read_unit(folder / UNIT_FILE)
        except (OSError, ValueError) as e:
            return f"its calibration document is unusable ({e})"
        if doc.get("unit_id") != unit_id or info.get("unit_id") != unit_id:
            return f"it holds the calibration of unit {doc.get('unit_id')!r}, not {unit_id!r}"
        return None

    return problem


def _model_info(folder: Path, mv: Any) -> dict[str, Any]:
    """What version.json says of a downloaded force model, beyond the version itself."""
    missing = [f for f in MODEL_FILES if not (folder / f).is_file()]
    if missing:  # a broken registered model is an error, not a reason to go offline
        raise ValueError(f"{mv.name} version {mv.version} ({mv.source}) has no {' or '.join(missing)}")
    meta, _ = open_model(folder)  # ModelRefused (a ValueError): the registered version is broken
    return {"checkpoint_sha256": meta.get("checkpoint_sha256"), "onnx_sha256": meta["onnx_sha256"]}


def _signed_model_fields(folder: Path, mv: Any) -> dict[str, Any]:
    """What the lab's signed manifest says of a published force model (its checkpoint and graph), once
    the graph is the one it names. Every file's hash was checked against the manifest already; the
    MLmodel is parsed once, when the client opens the folder and checks it against the graph."""
    missing = [f for f in MODEL_FILES if not (folder / f).is_file()]
    if missing:
        raise ValueError(f"{mv.name} version {mv.version} ({mv.source}) has no {' or '.join(missing)}")
    described = {k: mv.describe.get(k) for k in ("checkpoint_sha256", "onnx_sha256")}
    if file_sha256([folder / ONNX_FILE]) != described["onnx_sha256"]:
        raise ValueError(f"its {ONNX_FILE} is not the graph its manifest describes (onnx_sha256)")
    return described


def _unit_info(unit_id: str) -> Describe:
    """What version.json says of a downloaded unit calibration: a checked document of that unit."""

    def info(folder: Path, mv: Any) -> dict[str, Any]:
        path = folder / UNIT_FILE
        if not path.is_file():
            raise ValueError(f"{mv.name} version {mv.version} ({mv.source}) has no {UNIT_FILE}")
        sha, registered = (
            file_sha256([path]),
            (getattr(mv, "tags", None) or {}).get(store.CALIBRATION_SHA_TAG),
        )
        if sha != registered:  # the document's bytes as registered, or a version not to run
            raise ValueError(
                f"{mv.name} version {mv.version}: its {UNIT_FILE} (sha256 {sha[:12]}…) is not the document "
                f"registered (tag {store.CALIBRATION_SHA_TAG}: {registered!r}); register it again with "
                "`needlecue calibrate`"
            )
        doc = read_unit(path)
        if doc.get("unit_id") != unit_id:
            raise ValueError(
                f"{mv.name} version {mv.version} holds the calibration of unit {doc.get('unit_id')!r}"
            )
        return {"unit_id": unit_id, "calibration_sha256": sha}

    return info


def _download(
    mv: Any,
    alias: str,
    target: Path,
    registry_uri: str,
    describe: Describe = _model_info,
    only: tuple[str, ...] | None = None,
) -> Path:
    """Download a model version (or just the files `only` names) into a temp sibling of `target`, check
    it and describe it with `describe(folder, mv)` (a broken version raises ValueError), then swap it in
    (never a partial copy)."""
    import mlflow
    from mlflow.exceptions import MlflowException

    with _staging(target, alias) as tmp:
        with _quiet_downloads(), store.fluent(registry_uri):  # models:/ URIs resolve in the registry
            # by version, not alias: the alias may move between resolving it and downloading
            try:
                if only is None:
                    mlflow.artifacts.download_artifacts(
                        artifact_uri=f"models:/{mv.name}/{mv.version}",
                        dst_path=str(tmp),
                        tracking_uri=registry_uri,
                    )
                else:
                    _download_files(mv, only, tmp, registry_uri)
            except MlflowException as e:
                raise store.RegistryUnreachable(
                    f"downloading {mv.name} version {mv.version} from {registry_uri} failed: {e}"
                ) from e
        _write_version(tmp, mv, alias, describe(tmp, mv), registry_uri)
    return target


@contextlib.contextmanager
def _staging(target: Path, alias: str) -> Iterator[Path]:
    """A temp sibling of `target` to download into, swapped in for `target` when the block ends (by
    renames: a reader sees the old copy or the new, never part of one), deleted if the block fails."""
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{alias}-download-", dir=target.parent))
    tmp.chmod(0o755)  # mkdtemp's 0700 would hide a shared cache's copy from other users
    try:
        yield tmp
        _swap_in(tmp, target)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def _write_version(
    folder: Path, mv: Any, alias: str, described: dict[str, Any], source: str, extra: dict | None = None
) -> None:
    """version.json: which version of which model, from where and when, and what `describe` found."""
    info = {
        "name": mv.name,
        "version": str(mv.version),
        "alias": alias,
        "run_id": mv.run_id,
        "source": mv.source,
        **described,
        "tracking_uri": source,
        "fetched_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        **(extra or {}),
    }
    (folder / VERSION_FILE).write_text(json.dumps(info, indent=2) + "\n")


def _download_files(mv: Any, files: tuple[str, ...], folder: Path, registry_uri: str) -> None:
    """Download `files` of a model version into `folder`, each by itself: a logged model holds more
    than a client runs (environment files, input examples), and through a tracking server every file
    costs requests (22 for the whole of a force model, 12 for MLmodel and model.onnx). A file the
    version lacks is left out: `describe` then names it (a broken version, not an unreachable one)."""
    import mlflow
    from mlflow import MlflowClient
    from mlflow.exceptions import MlflowException

    root = MlflowClient(registry_uri, registry_uri).get_model_version_download_uri(mv.name, mv.version)
    for file in files:
        try:
            mlflow.artifacts.download_artifacts(
                artifact_uri=f"{root.rstrip('/')}/{file}", dst_path=str(folder), tracking_uri=registry_uri
            )
        except FileNotFoundError:
            pass
        except MlflowException as e:
            if e.error_code != "RESOURCE_DOES_NOT_EXIST":
                raise


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
        if read_version(target) is None:
            if old is not None and not target.exists():
                os.replace(old / "copy", target)  # put the previous copy back rather than none
            raise
        shutil.rmtree(new, ignore_errors=True)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)
