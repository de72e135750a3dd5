"""Publishing what simulators run, out of the tracking server's path: every alias of the lab's registered
models (`needle-force-<angle>@champion`, `needle-unit-<id>@current`, ...) copied to the published bucket
of the team's object store, as immutable objects named by their sha256 and one signed manifest per model
and alias (the format: `needlecue_runtime.registry.manifest`).

`plan` compares the registry with the bucket and says what is out of date; `publish` applies it:
objects first (each only if missing), then the manifest, so a simulator never finds a manifest whose
files are not there. Publishing twice changes nothing. An alias that is gone has its manifest withdrawn
(a simulator keeps what it runs: "not found" is not a reason to stop). Objects are never deleted: a
simulator offline since last week may still ask for one. What is published is checked first as a client
checks it (`needlecue_client.cache.download_checked`): a broken version is not published.
"""

from __future__ import annotations

import base64
import getpass
import hashlib
import logging
import socket
import tempfile
import time
from collections.abc import Collection
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Protocol

from needlecue_client.cache import download_checked
from needlecue_client.copies import read_version
from needlecue_runtime.registry import manifest as signed
from needlecue_runtime.registry import store

log = logging.getLogger(__name__)

BUCKET = "published"
MODEL_PREFIXES = ("needle-force-", "needle-unit-")
IMMUTABLE = "public, max-age=31536000, immutable"  # an object's bytes never change: cache it anywhere
DESCRIBED = ("checkpoint_sha256", "onnx_sha256", "unit_id", "calibration_sha256")


class Lab(Protocol):
    """What publishing needs of the team stack (`pipeline.team.stack.Stack` is one)."""

    @property
    def settings(self) -> dict[str, Any]: ...  # "publish_private_key" (base64)

    def s3_client(self) -> Any: ...  # boto3, with write access to the published bucket


@dataclass(frozen=True)
class Target:
    """Where and as whom the lab publishes: the bucket, a client that may write it, the signing key."""

    s3: Any
    bucket: str
    private_key: bytes
    who: str

    @classmethod
    def of(cls, lab: Lab, who: str | None = None) -> Target:
        key = base64.b64decode(lab.settings["publish_private_key"])
        return cls(lab.s3_client(), BUCKET, key, who or f"{getpass.getuser()}@{socket.gethostname()}")

    @property
    def public_key(self) -> bytes:
        return signed.public_of(self.private_key)


@dataclass(frozen=True)
class Change:
    """One manifest to write (`publish`: the alias's version is `version`) or to delete (`withdraw`);
    `refused`: a version that could not be published, `why` says why (it is not what a client runs)."""

    action: str
    name: str
    alias: str
    version: str | None
    why: str

    def __str__(self) -> str:
        if self.action == "refused":
            return f"{self.name}@{self.alias}: v{self.version} not published ({self.why})"
        what = f"v{self.version}" if self.version else "withdraw"
        return f"{self.name}@{self.alias}: {self.action} {what} ({self.why})"


def wanted(client: Any, names: Collection[str] | None = None) -> dict[tuple[str, str], Any]:
    """Every alias of the project's registered models (or of those `names`) and the ModelVersion it
    points to."""
    found: dict[tuple[str, str], Any] = {}
    for model in _models(client, names):
        for alias, version in sorted((model.aliases or {}).items()):
            found[(model.name, alias)] = client.get_model_version(model.name, str(version))
    return found


def _models(client: Any, names: Collection[str] | None) -> list[Any]:
    from mlflow.exceptions import MlflowException

    if names is not None:  # a webhook named them: one request each, not a search of the registry
        models = []
        for name in sorted(set(names)):
            try:
                models.append(client.get_registered_model(name))
            except MlflowException as e:
                if e.error_code not in ("RESOURCE_DOES_NOT_EXIST", "PERMISSION_DENIED"):
                    raise  # (with workspaces on, a model that is not there is "denied")
        return [m for m in models if m.name.startswith(MODEL_PREFIXES)]
    models, token = [], None
    while True:
        page = client.search_registered_models(filter_string="name LIKE 'needle-%'", page_token=token)
        models += [m for m in page if m.name.startswith(MODEL_PREFIXES)]
        token = page.token
        if not token:
            return models


def manifests(target: Target, names: Collection[str] | None = None) -> dict[tuple[str, str], bytes]:
    """The manifests in the bucket (of `names` only, if given), by (name, alias), as stored (not yet
    verified)."""
    found: dict[tuple[str, str], bytes] = {}
    for prefix in (
        [signed.MANIFESTS] if names is None else [f"{signed.MANIFESTS}{n}/" for n in sorted(set(names))]
    ):
        found |= _manifests_under(target, prefix)
    return found


def _manifests_under(target: Target, prefix: str) -> dict[tuple[str, str], bytes]:
    found: dict[tuple[str, str], bytes] = {}
    pages = target.s3.get_paginator("list_objects_v2").paginate(Bucket=target.bucket, Prefix=prefix)
    for page in pages:
        for obj in page.get("Contents", []):
            rest = obj["Key"][len(signed.MANIFESTS) :]
            name, _, file = rest.partition("/")
            if file.endswith(".json") and "/" not in file:
                body = target.s3.get_object(Bucket=target.bucket, Key=obj["Key"])["Body"].read()
                found[(name, file[: -len(".json")])] = body
    return found


def plan(client: Any, target: Target, names: Collection[str] | None = None) -> list[Change]:
    """What is out of date in the bucket against the registry (nothing: an empty list), for every
    model or only `names`."""
    want, have = wanted(client, names), manifests(target, names)
    changes = []
    for (name, alias), mv in sorted(want.items()):
        why = _stale(have.get((name, alias)), mv, target, name, alias)
        if why:
            changes.append(Change("publish", name, alias, str(mv.version), why))
    for name, alias in sorted(set(have) - set(want)):
        changes.append(Change("withdraw", name, alias, None, "the alias is gone from the registry"))
    return changes


def _stale(document: bytes | None, mv: Any, target: Target, name: str, alias: str) -> str | None:
    """Why the published manifest of `name@alias` is not `mv`'s, or None if it is (objects included)."""
    if document is None:
        return "not published"
    try:
        body = signed.verify(document, target.public_key, f"{name}@{alias}")
    except signed.ManifestRefused as e:
        return f"its manifest is refused: {e}"
    if (str(body["version"]), body["source"]) != (str(mv.version), mv.source):
        return f"published v{body['version']}, the registry's is v{mv.version}"
    missing = [f for f, e in body["files"].items() if not _has(target, signed.object_key(e["sha256"]))]
    return f"objects missing: {', '.join(sorted(missing))}" if missing else None


def _has(target: Target, key: str) -> bool:
    from botocore.exceptions import ClientError

    try:
        target.s3.head_object(Bucket=target.bucket, Key=key)
    except ClientError as e:
        if e.response.get("ResponseMetadata", {}).get("HTTPStatusCode") == 404:
            return False
        raise
    return True


def publish(
    registry_uri: str, target: Target, *, names: Collection[str] | None = None, check_only: bool = False
) -> list[Change]:
    """Bring the bucket up to date with the registry at `registry_uri` (read with the credentials in
    the environment), for every model or only `names`; returns what was (with `check_only`: what would
    be) changed, a version that could not be published as a `refused` change."""
    client = store.connect(registry_uri, must_exist=True)
    changes = plan(client, target, names)
    if check_only:
        return changes
    done = []
    for change in changes:
        t0 = time.monotonic()
        if change.action == "withdraw":
            target.s3.delete_object(Bucket=target.bucket, Key=signed.manifest_key(change.name, change.alias))
        else:
            mv = client.get_model_version(change.name, change.version)
            try:
                put_version(mv, change.alias, registry_uri, target)
            except ValueError as e:  # a broken registered version: never published; the others go on
                done.append(replace(change, action="refused", why=str(e)))
                log.error("cannot publish %s", done[-1])
                continue
        done.append(change)
        log.info("published %s in %.2f s", change, time.monotonic() - t0)
    return done


def put_version(mv: Any, alias: str, registry_uri: str, target: Target) -> dict[str, Any]:
    """Publish one version under `alias`: its checked files as objects, then its signed manifest.
    Returns the signed document."""
    with tempfile.TemporaryDirectory(prefix="needlecue-publish-") as tmp:
        folder = download_checked(mv, alias, Path(tmp) / "copy", registry_uri)
        info = read_version(folder) or {}
        files = {}
        for path in sorted(p for p in folder.iterdir() if p.is_file() and p.name != "version.json"):
            data = path.read_bytes()
            sha = hashlib.sha256(data).hexdigest()
            if not _has(target, signed.object_key(sha)):
                target.s3.put_object(
                    Bucket=target.bucket, Key=signed.object_key(sha), Body=data, CacheControl=IMMUTABLE
                )
            files[path.name] = {"sha256": sha, "size": len(data)}
    body = {
        "name": mv.name,
        "alias": alias,
        "version": str(mv.version),
        "run_id": mv.run_id,
        "source": mv.source,
        "files": files,
        "describe": {k: info[k] for k in DESCRIBED if k in info},
        "published_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "published_by": target.who,
    }
    document = signed.sign(body, target.private_key)
    target.s3.put_object(
        Bucket=target.bucket,
        Key=signed.manifest_key(mv.name, alias),
        Body=signed.canonical(document),
        ContentType="application/json",
        CacheControl="no-cache",  # a cache in front revalidates a manifest each time (objects: forever)
    )
    return document
