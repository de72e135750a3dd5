"""The signed manifest of a published version: what verifies, and why anything else is refused."""

from __future__ import annotations

import base64
import json

import pytest

from needlecue_runtime.registry import manifest as signed

SHA = "ab" * 32


def _body() -> dict:
    return {
        "name": "needle-force-30", "alias": "champion", "version": "4", "run_id": "r1",
        "source": "models:/m-1", "files": {"model.onnx": {"sha256": SHA, "size": 10}},
        "describe": {"onnx_sha256": SHA}, "published_utc": "2026-11-26T00:00:00Z", "published_by": "lab",
    }  # fmt: skip


@pytest.fixture
def key() -> bytes:
    return signed.new_private_key()


def test_a_signed_manifest_verifies_with_the_public_half_only(key):
    # Given a manifest signed with the lab's key, as stored (canonical bytes)
    stored = signed.canonical(signed.sign(_body(), key))
    # When a simulator verifies it with the public key
    body = signed.verify(stored, signed.public_of(key), "m.json")
    # Then it reads the manifest as signed, with the key's id
    assert body["version"] == "4" and body["files"]["model.onnx"]["sha256"] == SHA
    assert body["format"] == signed.FORMAT and body["key_id"] == signed.key_id(signed.public_of(key))


@pytest.mark.parametrize(
    ("tamper", "why"),
    [
        (lambda d: {**d, "manifest": {**d["manifest"], "version": "5"}}, "changed after signing"),
        (lambda d: {"manifest": d["manifest"]}, "unsigned"),
        (lambda d: {**d, "signature": "not base64!"}, "changed after signing"),
        (lambda d: {"signature": d["signature"]}, "no 'manifest' object"),
        (lambda d: signed.sign(d["manifest"], signed.new_private_key()), "signed by another key"),
    ],
    ids=["changed", "unsigned", "garbled signature", "no manifest", "another key"],
)
def test_anything_but_the_lab_s_signed_manifest_is_refused_with_the_reason(key, tamper, why):
    # Given a signed manifest, then changed
    doc = tamper(signed.sign(_body(), key))
    # Then verifying it is refused, naming where and why
    with pytest.raises(signed.ManifestRefused, match=f"m.json.*{why}"):
        signed.verify(json.dumps(doc).encode(), signed.public_of(key), "m.json")


def test_a_signed_manifest_without_its_fields_or_with_bad_file_entries_is_refused(key):
    # Given manifests the lab's key signed, but lacking a field, or with a file entry that is no hash
    lacking = {k: v for k, v in _body().items() if k != "source"}
    bad_file = {**_body(), "files": {"model.onnx": {"sha256": "xyz", "size": 10}}}
    # Then each is refused for what it lacks
    with pytest.raises(signed.ManifestRefused, match="lacks source"):
        signed.verify(signed.sign(lacking, key), signed.public_of(key), "m.json")
    with pytest.raises(signed.ManifestRefused, match="sha256 and size"):
        signed.verify(signed.sign(bad_file, key), signed.public_of(key), "m.json")


def test_the_public_key_setting_is_checked():
    # Then a missing, non-base64 or wrong-length key is a clear error naming the variable
    with pytest.raises(signed.ManifestRefused, match=signed.PUBLIC_KEY_ENV):
        signed.public_key(None)
    with pytest.raises(signed.ManifestRefused, match="not base64"):
        signed.public_key("%%%")
    with pytest.raises(signed.ManifestRefused, match="16 bytes"):
        signed.public_key(base64.b64encode(b"x" * 16).decode())
