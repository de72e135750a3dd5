"""Fetching a registered force model, and an estimator unit's calibration, into the simulator's local
cache.

`fetch` resolves `models:/needle-force-<angle>@<alias>` and keeps one copy per (model, alias) under the
cache folder (`needlecue_client.copies`): `<cache>/needle-force-<angle>/<alias>/` holding MLmodel,
model.onnx and version.json. A copy is downloaded only when the alias points elsewhere: from the
registry (`from_registry`) or from a published bucket (`from_bucket`), checked (`verify`). When the
source cannot be reached the cached copy is used with a warning (`offline`), so a simulator keeps
working offline. `poll_alias` is the quick "where does the alias point now" request of a client that
follows its alias. `fetch_unit` does the same for `models:/needle-unit-<unit_id>@current`, a unit's
calibration document. mlflow is imported inside the functions that talk to the registry.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import needlecue_client.published as published
from needlecue_client.copies import default_cache_dir, is_copy_of, read_version
from needlecue_client.folder import ONNX_FILE
from needlecue_client.from_bucket import PublishedVersion, fetch_published, published_manifest
from needlecue_client.from_registry import download, resolve
from needlecue_client.offline import offline_copy
from needlecue_client.verify import (
    MODEL_FILES,
    Describe,
    Verify,
    model_info,
    model_problem,
    signed_model_fields,
    unit_info,
    unit_problem,
)
from needlecue_runtime.registry import mlflow_env, store
from needlecue_runtime.unit_calibration import FILE as UNIT_FILE

# A poll is one metadata request that must not hold up an insertion's start: against an HTTP registry it
# gets a short timeout and no retries (a failed poll is simply tried again at the next interval).
_POLL_HTTP_ENV = {"MLFLOW_HTTP_REQUEST_TIMEOUT": "2", "MLFLOW_HTTP_REQUEST_MAX_RETRIES": "0"}

MODEL_HINT = "run `make repro` to train and register the models"

UNIT_PREFIX = "needle-unit-"  # store.unit_model_name's

UNIT_HINT = "record a calibration batch with that unit and run `needlecue calibrate BATCH_DIR`"


def source_uri(tracking_uri: str | None = None) -> str:
    """Where a client fetches from: `tracking_uri` if given, else the published bucket of
    `$NEEDLECUE_PUBLISHED_URL` if set, else MLflow's tracking URI (read at call time)."""
    return tracking_uri or published.default_location() or store.tracking_uri()


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
        model_info,
        model_problem(name, angle_deg),
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
        found, _ = published_manifest(uri, name, alias, hint)
        return PublishedVersion(found)
    with mlflow_env.environment(_POLL_HTTP_ENV):
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
        return resolve(store.connect(uri, must_exist=True), name, alias, uri, hint)


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
        unit_info(unit_id),
        unit_problem(name, unit_id),
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
        light = signed_model_fields if describe is model_info else describe  # parsed once, to run it
        return fetch_published(
            name, alias, target, cached, registry_uri, (file, sha_key), hint, light, problem
        )
    try:
        with mlflow_env.patience():
            mv = resolve(store.connect(registry_uri, must_exist=True), name, alias, registry_uri, hint)
    except store.RegistryUnreachable as e:
        return offline_copy(target, cached, uri, e, problem)
    if (
        cached is not None
        and cached.get("name") == name
        and is_copy_of(cached, mv.version, mv.source, target, file, sha_key)
    ):
        return target  # already that version, intact: no download
    try:
        with mlflow_env.patience():
            return download(mv, alias, target, registry_uri, describe, only)
    except (OSError, store.RegistryUnreachable) as e:  # the connection dropped mid-download
        return offline_copy(target, cached, uri, e, problem)


def download_checked(mv: Any, alias: str, target: Path, registry_uri: str) -> Path:
    """A model version's files a simulator runs, downloaded from the registry into `target` and checked
    as a client checks them (a broken version raises ValueError): what the lab publishes."""
    if mv.name.startswith(UNIT_PREFIX):
        unit_id = mv.name[len(UNIT_PREFIX) :]
        return download(mv, alias, target, registry_uri, unit_info(unit_id), (UNIT_FILE,))
    return download(mv, alias, target, registry_uri, model_info, MODEL_FILES)
