"""Reading a lab's published bucket: signed manifests by conditional GET, objects by hash.

A simulator pointed at a published bucket (`NEEDLECUE_PUBLISHED_URL=http://<s3 host:port>/<bucket>`,
with read-only S3 credentials in `AWS_ACCESS_KEY_ID` / `AWS_SECRET_ACCESS_KEY` and the lab's public key
in `NEEDLECUE_PUBLISH_PUBLIC_KEY`) never talks to the MLflow tracking server: `needlecue_client.cache`
fetches through a `Bucket` when its location is `published+<url>`. A poll is one GET of the manifest with
`If-None-Match: <the ETag last seen>`, answered 304 when nothing changed. Every manifest is verified
(`needlecue_runtime.registry.manifest.verify`) before a field is read, and every object's sha256 and
size before its bytes are written anywhere. A request is a plain HTTP GET signed with AWS Signature
Version 4 by botocore's signer, on a kept-alive connection (one per thread): a simulator needs
botocore, not boto3's clients, and a poll costs it a fraction of a millisecond of CPU.
"""

from __future__ import annotations

import hashlib
import http.client
import os
import threading
from dataclasses import dataclass, field
from typing import Any
from urllib.parse import quote, urlsplit

from needlecue_runtime.registry import manifest as signed
from needlecue_runtime.registry import store

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
    keys: tuple[str, str]  # read-only (access key id, secret), from AWS_ACCESS_KEY_ID / _SECRET_ACCESS_KEY
    region: str = "us-east-1"
    _local: threading.local = field(default_factory=threading.local)  # one kept-alive connection per thread
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
        keys = (os.environ.get("AWS_ACCESS_KEY_ID", ""), os.environ.get("AWS_SECRET_ACCESS_KEY", ""))
        if not all(keys):
            raise store.RegistryUnreachable(
                f"no S3 keys to read the published bucket {url} with: set AWS_ACCESS_KEY_ID and "
                "AWS_SECRET_ACCESS_KEY (the simulator's environment from `needlecue team env simulator`)"
            )
        region = os.environ.get("AWS_DEFAULT_REGION", "us-east-1")
        return cls(location(url), key, f"{parts.scheme}://{parts.netloc}", bucket, keys, region)

    @property
    def host(self) -> str:
        return self.endpoint.split("://", 1)[1]

    @property
    def where(self) -> str:
        return f"{self.endpoint}/{self.name}"

    def _get(
        self, key: str, etag: str | None = None, timeout: float = POLL_TIMEOUT_S
    ) -> tuple[int, bytes, str]:
        """(status, body, ETag) of one signed GET of `key` (If-None-Match `etag`), on this thread's
        kept-alive connection (one retry on a connection the store closed meanwhile)."""
        path = "/" + quote(f"{self.name}/{key}", safe="/-_.~")
        headers = signed_headers(self.endpoint + path, self.keys, self.region)
        if etag:
            headers["If-None-Match"] = etag
        for attempt in (1, 2):
            conn = self._connection(timeout)
            try:
                conn.request("GET", path, headers=headers)
                answer = conn.getresponse()
                return answer.status, answer.read(), answer.getheader("ETag") or ""
            except (http.client.RemoteDisconnected, BrokenPipeError, ConnectionResetError) as e:
                self._local.conn = None
                conn.close()
                if attempt == 2:
                    raise store.RegistryUnreachable(f"the published bucket {self.where}: {e}") from None
            except (OSError, http.client.HTTPException) as e:  # refused, timed out, not HTTP
                self._local.conn = None
                conn.close()
                raise store.RegistryUnreachable(f"the published bucket {self.where}: {e}") from None
        raise AssertionError("unreachable")

    def _connection(self, timeout: float) -> http.client.HTTPConnection:
        conn = getattr(self._local, "conn", None)
        if conn is None:
            cls = (
                http.client.HTTPSConnection
                if self.endpoint.startswith("https")
                else http.client.HTTPConnection
            )
            conn = self._local.conn = cls(self.host, timeout=timeout)
        conn.timeout = timeout
        if conn.sock is not None:
            conn.sock.settimeout(timeout)
        return conn

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
        status, document, etag = self._get(key, seen[0] if seen else None)
        if status == 304 and seen is not None:
            return seen[1], None, seen[0]
        if self._failed(status, key, document):
            return None
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
        status, data, _ = self._get(key, timeout=OBJECT_TIMEOUT_S)
        if self._failed(status, key, data):
            raise PublishedRefused(f"{self.where}/{key}: missing (the manifest names it)")
        sha = hashlib.sha256(data).hexdigest()
        if sha != entry["sha256"] or len(data) != entry["size"]:
            raise PublishedRefused(
                f"{self.where}/{key}: refused, its bytes (sha256 {sha[:12]}…, {len(data)} bytes) are not "
                f"the manifest's ({entry['sha256'][:12]}…, {entry['size']} bytes): changed or damaged"
            )
        return data

    def _failed(self, status: int, key: str, body: bytes) -> bool:
        """True for no such key (404); raises `RegistryUnreachable` for any answer but 200 and 404."""
        if status == 200:
            return False
        if status == 404:
            return True
        code = _error_code(body)
        if status in (401, 403):
            raise store.RegistryUnreachable(
                f"the published bucket {self.where} refused the credentials ({code}): a simulator reads "
                "it with the read-only keys of `needlecue team env simulator` (AWS_ACCESS_KEY_ID, ...)"
            )
        raise store.RegistryUnreachable(f"the published bucket {self.where}/{key}: HTTP {status} {code}")


def _error_code(body: bytes) -> str:
    """S3's <Code> of an error answer, or ''."""
    text = body[:2000].decode("utf-8", "replace")
    start, end = text.find("<Code>"), text.find("</Code>")
    return text[start + 6 : end] if 0 <= start < end else ""


def signed_headers(url: str, keys: tuple[str, str], region: str) -> dict[str, str]:
    """The headers of a GET of `url` (an S3 object, no query, empty body) signed with AWS Signature
    Version 4 by botocore's own S3 signer: botocore alone, without boto3's sessions and clients."""
    from botocore.auth import S3SigV4Auth
    from botocore.awsrequest import AWSRequest
    from botocore.credentials import Credentials

    request = AWSRequest(method="GET", url=url)
    S3SigV4Auth(Credentials(*keys), "s3", region).add_auth(request)
    return dict(request.headers.items())


_buckets: dict[str, Bucket] = {}
_buckets_lock = threading.Lock()


def bucket(uri: str) -> Bucket:
    """The `Bucket` of a location, one per process (so polls reuse its connections and ETags)."""
    with _buckets_lock:
        found = _buckets.get(uri)
        if found is None:
            found = _buckets[uri] = Bucket.at(uri)
        return found
