"""What an ingested batch's outputs depend on, as one hash: its folder's bytes, the ingest params, the code
that decides them and the libraries' versions. A batch whose stored fingerprint matches is not parsed
again (`pipeline.rig.batch_store`)."""

from __future__ import annotations

import hashlib
import json
from importlib import metadata
from pathlib import Path
from typing import Any

from pipeline.config import IngestParams
from pipeline.rig.format import ID_PATTERN

# Bump when the output layout or meaning changes: every stored batch is then parsed again.
OUTPUT_VERSION = 3  # 2: batch.json carries `purpose`; 3: and `samples_sha256`
# The modules of pipeline/rig/ that decide a batch's outputs, hashed into its fingerprint so a
# code change parses every batch again (datadocs.py only renders the reports: not here).
CODE_FILES = (
    "format.py",
    "problems.py",
    "batch_yaml.py",
    "csvfile.py",
    "expectations.py",
    "reader.py",
    "repeats.py",
    "plausible.py",
    "tdmsfile.py",
    "ingest.py",
    "fingerprint.py",
    "batch_store.py",
)


def _code_sha256() -> str:
    """SHA-256 of the CODE_FILES, by name and bytes."""
    h = hashlib.sha256()
    here = Path(__file__).parent
    for name in CODE_FILES:
        h.update(f"rig/{name}".encode() + b"\0" + (here / name).read_bytes())
    return h.hexdigest()


def fingerprint(batch_dir: Path, params: IngestParams, source_dir: str | None = None) -> dict[str, Any]:
    """What a batch's outputs depend on: its files' names and bytes, params, code, library versions.

    `source_dir` is the folder's name as the ingest stage gives it (default `str(batch_dir)`), so a
    caller reading the same folder by another path (absolute, say) gets the same fingerprint."""
    h = hashlib.sha256()
    files = sorted(
        (p for p in batch_dir.rglob("*") if p.is_file()), key=lambda p: p.relative_to(batch_dir).as_posix()
    )
    for p in files:
        h.update(p.relative_to(batch_dir).as_posix().encode() + b"\0")
        try:
            with p.open("rb") as f:  # read-only, like every access to the input folders
                for chunk in iter(lambda f=f: f.read(1 << 20), b""):
                    h.update(chunk)
        except OSError as e:  # the parse says so, with the file; the fingerprint keeps the reason
            h.update(f"unreadable: {e.strerror}".encode())
        h.update(b"\0")
    parts: dict[str, Any] = {
        "output_version": OUTPUT_VERSION,
        "source_dir": str(batch_dir) if source_dir is None else source_dir,
        "files_sha256": h.hexdigest(),
        "n_files": len(files),
        "params": params.model_dump(mode="json"),
        "code_sha256": _code_sha256(),
        "id_pattern": ID_PATTERN.pattern,  # lives in client/needlecue_runtime/vocab.py, outside CODE_FILES
        "versions": {m: metadata.version(m) for m in ("great_expectations", "pandas", "pyarrow", "npTDMS")},
    }
    parts["fingerprint"] = hashlib.sha256(json.dumps(parts, sort_keys=True).encode()).hexdigest()
    return parts
