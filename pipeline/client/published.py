"""Reading a lab's published bucket: signed manifests by conditional GET, objects by hash.

A simulator pointed at a published bucket (`NEEDLECUE_PUBLISHED_URL=http://<s3 host:port>/<bucket>`,
with read-only S3 credentials in `AWS_ACCESS_KEY_ID` / `AWS_SECRET_ACCESS_KEY` and the lab's public key
in `NEEDLECUE_PUBLISH_PUBLIC_KEY`) never talks to the MLflow tracking server: `pipeline.client.cache`
fetches through a `Bucket` when its location is `published+<url>`. A poll is one GET of the manifest with
`If-None-Match: <the ETag last seen>`, answered 304 when nothing changed. Every manifest is verified
(`pipeline.registry.manifest.verify`) before a field is read, and every object's sha256 and size before
its bytes are written anywhere. boto3 is imported when a bucket is first used.
"""

from __future__ import annotations

import hashlib
import os
import threading
from dataclasses import dataclass, field
from typing import Any
from urllib.parse import urlsplit

from pipeline.registry import manifest as signed
from pipeline.registry import store

PUBLISHED_ENV = "NEEDLECUE_PUBLISHED_URL"
SCHEME = "published+"
POLL_TIMEOUT_S = 2.0  # a poll must not hold up an insertion's start (as over the tracking server)
OBJECT_TIMEOUT_S = 30.0


class PublishedRefused(store.RegistryUnreachable):
    """The published copy is not the lab's (a manifest unsigned, tampered or signed by another key; an
    object whose hash or size is not the manifest's): nothing of it runs. A subclass of
    RegistryUnreachable, so that a verified cached copy keeps running, as when offline."""


def location(url: str) -> str:
    """The location string a client fetches from for a published bucket URL (`published+http://...`)."""
    return url if url.startswith(SCHEME) else SCHEME + url


def is_published(uri: str | None) -> bool:
    return bool(uri) and str(uri).startswith(SCHEME)


def default_location() -> str | None:
    """`published+$NEEDLECUE_PUBLISHED_URL` if that is set (read at call time), else None."""
    url = os.environ.get(PUBLISHED_ENV)
    return location(url) if url else None


@dataclass
class Bucket:
    """One published bucket as a simulator reads it: the manifests it has seen (by ETag) and the
    lab's public key."""

    uri: str  # published+http://host:port/bucket
    public_key: bytes
    endpoint: str
    name: str
    _client: Any = None
    _seen: dict[tuple[str, str], tuple[str, dict[str, Any]]] = field(default_factory=dict)
    _lock: threading.Lock = field(default_factory=threading.Lock)

    @classmethod
    def at(cls, uri: str) -> Bucket:
        url = uri[len(SCHEME) :] if uri.startswith(SCHEME) else uri
        parts = urlsplit(url)
        bucket = parts.path.strip("/")
        if parts.scheme not in ("http", "https") or not parts.netloc or not bucket or "/" in bucket:
            raise ValueError(f"{PUBLISHED_ENV} {url!r}: expected http(s)://<S3 host:port>/<bucket>")
        try:
            key = signed.public_key(os.environ.get(signed.PUBLIC_KEY_ENV))
        except signed.ManifestRefused as e:
            raise PublishedRefused(str(e)) from None
        return cls(location(url), key, f"{parts.scheme}://{parts.netloc}", bucket)

    @property
    def where(self) -> str:
        return f"{self.endpoint}/{self.name}"

    def client(self) -> Any:
        """The S3 client (made once; boto3's clients are thread-safe): short timeouts, no retries."""
        if self._client is None:
            import boto3
            from botocore.config import Config

            self._client = boto3.client(
                "s3", endpoint_url=self.endpoint,
                region_name=os.environ.get("AWS_DEFAULT_REGION", "us-east-1"),
                config=Config(retries={"max_attempts": 1}, connect_timeout=POLL_TIMEOUT_S,
                              read_timeout=OBJECT_TIMEOUT_S, max_pool_connections=32),
            )  # fmt: skip
        return self._client

    def remember(self, name: str, alias: str, etag: str, document: bytes) -> None:
        """A manifest as fetched before (a cached copy's): the next poll asks If-None-Match its ETag."""
        body = signed.verify(document, self.public_key, f"cached manifest of {name}@{alias}")
        with self._lock:
            self._seen[(name, alias)] = (etag, body)

    def forget(self, name: str, alias: str) -> None:
        with self._lock:
            self._seen.pop((name, alias), None)

    def etag(self, name: str, alias: str) -> str | None:
        with self._lock:
            seen = self._seen.get((name, alias))
        return seen[0] if seen else None

    def manifest(self, name: str, alias: str) -> tuple[dict[str, Any], bytes | None, str] | None:
        """(verified manifest, its signed bytes or None when answered 304, ETag) of `name@alias`, or
        None if nothing is published under it. `PublishedRefused` for a manifest that is not the lab's
        or not of `name@alias`; `RegistryUnreachable` if the store cannot be asked."""
        key = signed.manifest_key(name, alias)
        with self._lock:
            seen = self._seen.get((name, alias))
        args = {"Bucket": self.name, "Key": key} | ({"IfNoneMatch": seen[0]} if seen else {})
        try:
            got = self._call(lambda: self.client().get_object(**args), key)
        except _NotModified:
            assert seen is not None
            return seen[1], None, seen[0]
        if got is None:
            return None
        document, etag = got["Body"].read(), got.get("ETag", "")
        where = f"{self.where}/{key}"
        try:
            body = signed.verify(document, self.public_key, where)
        except signed.ManifestRefused as e:
            raise PublishedRefused(str(e)) from None
        if (body["name"], body["alias"]) != (name, alias):
            raise PublishedRefused(f"{where}: refused, it is the manifest of {body['name']}@{body['alias']}")
        with self._lock:
            self._seen[(name, alias)] = (etag, body)
        return body, document, etag

    def object(self, entry: dict[str, Any]) -> bytes:
        """The bytes of one file of a manifest, checked against its sha256 and size."""
        key = signed.object_key(entry["sha256"])
        got = self._call(lambda: self.client().get_object(Bucket=self.name, Key=key), key)
        if got is None:
            raise PublishedRefused(f"{self.where}/{key}: missing (the manifest names it)")
        data = got["Body"].read()
        sha = hashlib.sha256(data).hexdigest()
        if sha != entry["sha256"] or len(data) != entry["size"]:
            raise PublishedRefused(
                f"{self.where}/{key}: refused, its bytes (sha256 {sha[:12]}…, {len(data)} bytes) are not "
                f"the manifest's ({entry['sha256'][:12]}…, {entry['size']} bytes): changed or damaged"
            )
        return data

    def _call(self, call: Any, key: str) -> Any:
        """`call()`, with S3's answers turned into ours: None for no such key, `_NotModified` for 304,
        `RegistryUnreachable` for no answer, a server error or refused credentials."""
        from botocore.exceptions import BotoCoreError, ClientError

        try:
            return call()
        except ClientError as e:
            status = e.response.get("ResponseMetadata", {}).get("HTTPStatusCode")
            code = e.response.get("Error", {}).get("Code")
            if status == 304 or code == "304":
                raise _NotModified from None
            if status == 404 or code in ("NoSuchKey", "404"):
                return None
            if status in (401, 403):
                raise store.RegistryUnreachable(
                    f"the published bucket {self.where} refused the credentials ({code}): a simulator "
                    "reads it with the read-only keys of `needlecue team env simulator`"
                ) from None
            raise store.RegistryUnreachable(f"the published bucket {self.where}: {code} ({status})") from None
        except (BotoCoreError, OSError) as e:
            raise store.RegistryUnreachable(f"the published bucket {self.where}: {e}") from None


class _NotModified(Exception):
    """The store answered 304: the manifest is the one seen last."""


_buckets: dict[str, Bucket] = {}
_buckets_lock = threading.Lock()


def bucket(uri: str) -> Bucket:
    """The `Bucket` of a location, one per process (so polls reuse its connections and ETags)."""
    with _buckets_lock:
        found = _buckets.get(uri)
        if found is None:
            found = _buckets[uri] = Bucket.at(uri)
        return found
