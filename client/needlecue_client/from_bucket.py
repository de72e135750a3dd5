"""Fetching from a published bucket (`needlecue_client.published`): the lab's signed manifest by
conditional GET, the files by their hashes, everything verified before it is written and swapped in."""

from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Any

import needlecue_client.published as published
from needlecue_client.copies import (
    MANIFEST_FILE,
    VERSION_FILE,
    ModelNotFound,
    is_copy_of,
    staging,
    write_version,
)
from needlecue_client.offline import offline_copy
from needlecue_client.verify import Describe, Verify
from needlecue_runtime.registry import store


class PublishedVersion:
    """What a client reads of a model version (as MLflow's ModelVersion), from a verified manifest."""

    def __init__(self, manifest: dict[str, Any]) -> None:
        self.name, self.version, self.source = manifest["name"], str(manifest["version"]), manifest["source"]
        self.run_id = manifest.get("run_id")
        self.describe = manifest.get("describe") or {}
        sha = self.describe.get("calibration_sha256")
        self.tags = {store.CALIBRATION_SHA_TAG: sha} if sha else {}


def published_manifest(uri: str, name: str, alias: str, hint: str) -> tuple[dict[str, Any], bytes | None]:
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


def fetch_published(
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
        found, document = published_manifest(uri, name, alias, hint)
        if is_copy_of(cached, found["version"], found["source"], target, file, sha_key):
            return target  # already that version, intact (the client checks the folder as it opens it)
        return _download_published(bucket, found, document, alias, target, describe)
    except store.RegistryUnreachable as e:  # PublishedRefused too: the verified cached copy runs
        return offline_copy(target, cached, f"{bucket.where} {name}@{alias}", e, problem)


def _download_published(
    bucket: published.Bucket,
    found: dict[str, Any],
    document: bytes | None,
    alias: str,
    target: Path,
    describe: Describe,
) -> Path:
    """The manifest's files, each checked against its hash, into a temp sibling of `target`, described
    and swapped in as `download` does."""
    if document is None:  # answered 304 for a manifest whose cached files are gone: fetch it whole
        bucket.forget(found["name"], alias)
        found, document = published_manifest(bucket.uri, found["name"], alias, "")
        assert document is not None
    with staging(target, alias) as tmp:
        for fname, entry in sorted(found["files"].items()):
            if fname in ("", ".", "..", VERSION_FILE, MANIFEST_FILE) or "/" in fname or "\\" in fname:
                raise published.PublishedRefused(
                    f"{bucket.where}: refused, the manifest names a file {fname!r}"
                )
            (tmp / fname).write_bytes(bucket.object(entry))
        mv = PublishedVersion(found)
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
        write_version(tmp, mv, alias, described, bucket.uri, extra)
    return target
