"""The signed manifest of a published model version: what a simulator runs, by hash, signed by the lab.

A lab publishes each alias of its registered models (`needle-force-<angle>@champion`,
`needle-unit-<id>@current`, ...) to a bucket of its object store (`pipeline.team.publish`): every file
a simulator runs as an immutable object named by its sha256 (`objects/sha256/<hex>`), and one small
manifest per model and alias (`manifests/<name>/<alias>.json`):

    {"manifest": {"format": "needlecue-published/1", "name", "alias", "version", "run_id", "source",
                  "files": {"MLmodel": {"sha256", "size"}, "model.onnx": {...}},
                  "describe": {...}, "published_utc", "published_by", "key_id"},
     "signature": "<base64 Ed25519 signature of the manifest's canonical JSON>"}

The signature is Ed25519: the lab holds the private key, a simulator only the public one, so a simulator
(or anyone who reads its disk) can check a manifest but never write one a fleet would accept. An HMAC key
would let every simulator that holds it publish. `verify` checks the signature before a field is read.
"""

from __future__ import annotations

import base64
import hashlib
import json
from collections.abc import Mapping
from typing import Any

FORMAT = "needlecue-published/1"
OBJECTS = "objects/sha256/"
MANIFESTS = "manifests/"
PUBLIC_KEY_ENV = "NEEDLECUE_PUBLISH_PUBLIC_KEY"  # base64 of the raw 32-byte Ed25519 public key
FIELDS = ("name", "alias", "version", "run_id", "source", "files", "describe", "published_utc")


class ManifestRefused(ValueError):
    """A manifest that is not the lab's: unsigned, tampered, signed by another key, or malformed."""


def object_key(sha256: str) -> str:
    return f"{OBJECTS}{sha256}"


def manifest_key(name: str, alias: str) -> str:
    return f"{MANIFESTS}{name}/{alias}.json"


def canonical(manifest: Mapping[str, Any]) -> bytes:
    """The bytes a signature covers: sorted keys, no spaces, UTF-8."""
    return json.dumps(manifest, sort_keys=True, separators=(",", ":"), ensure_ascii=False).encode()


def key_id(public_raw: bytes) -> str:
    """A short name of a public key (the first 16 hex digits of its sha256)."""
    return hashlib.sha256(public_raw).hexdigest()[:16]


def new_private_key() -> bytes:
    """A new Ed25519 private key, raw 32 bytes."""
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey
    from cryptography.hazmat.primitives.serialization import Encoding, NoEncryption, PrivateFormat

    return Ed25519PrivateKey.generate().private_bytes(Encoding.Raw, PrivateFormat.Raw, NoEncryption())


def public_of(private_raw: bytes) -> bytes:
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey
    from cryptography.hazmat.primitives.serialization import Encoding, PublicFormat

    key = Ed25519PrivateKey.from_private_bytes(private_raw)
    return key.public_key().public_bytes(Encoding.Raw, PublicFormat.Raw)


def sign(manifest: Mapping[str, Any], private_raw: bytes) -> dict[str, Any]:
    """The signed document of `manifest` (its `key_id` set to the signing key's)."""
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

    body = {**manifest, "format": FORMAT, "key_id": key_id(public_of(private_raw))}
    signature = Ed25519PrivateKey.from_private_bytes(private_raw).sign(canonical(body))
    return {"manifest": body, "signature": base64.b64encode(signature).decode()}


def public_key(text: str | None) -> bytes:
    """The raw public key from its base64 text (`NEEDLECUE_PUBLISH_PUBLIC_KEY`); a clear error if unusable."""
    if not text:
        raise ManifestRefused(
            f"no public key to check published manifests with: set {PUBLIC_KEY_ENV} (the simulator's "
            "environment from `needlecue team env simulator`)"
        )
    try:
        raw = base64.b64decode(text, validate=True)
    except ValueError as e:
        raise ManifestRefused(f"{PUBLIC_KEY_ENV} is not base64 ({e})") from e
    if len(raw) != 32:
        raise ManifestRefused(f"{PUBLIC_KEY_ENV} holds {len(raw)} bytes, an Ed25519 public key is 32")
    return raw


def verify(document: bytes | Mapping[str, Any], public_raw: bytes, where: str) -> dict[str, Any]:
    """The manifest of a signed document, once its signature verifies with `public_raw` and its fields
    are there; `ManifestRefused` naming `where` and the reason otherwise."""
    from cryptography.exceptions import InvalidSignature
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PublicKey

    try:
        doc = json.loads(document) if isinstance(document, bytes | str) else dict(document)
    except ValueError as e:
        raise ManifestRefused(f"{where}: not JSON ({e})") from e
    if not isinstance(doc, dict) or not isinstance(doc.get("manifest"), dict):
        raise ManifestRefused(f"{where}: not a signed manifest (no 'manifest' object)")
    if not isinstance(doc.get("signature"), str) or not doc["signature"]:
        raise ManifestRefused(f"{where}: unsigned (no 'signature')")
    body = doc["manifest"]
    try:
        signature = base64.b64decode(doc["signature"], validate=True)
        Ed25519PublicKey.from_public_bytes(public_raw).verify(signature, canonical(body))
    except (ValueError, InvalidSignature):
        ours, theirs = key_id(public_raw), body.get("key_id")
        why = (
            f"signed by another key ({theirs}, the lab's is {ours})"
            if theirs != ours
            else "its signature does not match its content (changed after signing)"
        )
        raise ManifestRefused(f"{where}: refused, {why}") from None
    if body.get("format") != FORMAT:
        raise ManifestRefused(f"{where}: format {body.get('format')!r}, this needlecue reads {FORMAT}")
    missing = [f for f in FIELDS if f not in body]
    if missing:
        raise ManifestRefused(f"{where}: the manifest lacks {', '.join(missing)}")
    files = body["files"]
    if not isinstance(files, dict) or not files or not all(_file_entry(v) for v in files.values()):
        raise ManifestRefused(f"{where}: 'files' must map each file to its sha256 and size")
    return body


def _file_entry(entry: Any) -> bool:
    return (
        isinstance(entry, dict)
        and isinstance(entry.get("sha256"), str)
        and len(entry["sha256"]) == 64
        and all(c in "0123456789abcdef" for c in entry["sha256"])
        and isinstance(entry.get("size"), int)
        and entry["size"] >= 0
    )
