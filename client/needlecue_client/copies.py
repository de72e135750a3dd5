"""The simulator's local copies of registered versions: `<cache>/<name>/<alias>/` with what was
fetched and its version.json (which version, from where, when, and what `needlecue_client.verify`
found), written into a temp sibling and swapped in by renames, so that a reader never sees half a
copy; and what a fetch ends in when there is no version to have (`ModelNotFound`) or the copy kept
is not to run (`CachedCopyRefused`)."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from needlecue_runtime.registry import store
from needlecue_runtime.vocab import file_sha256

DEFAULT_CACHE = Path("~/.cache/needlecue/models").expanduser()

CACHE_ENV = "NEEDLECUE_MODEL_CACHE"

VERSION_FILE = "version.json"

MANIFEST_FILE = "manifest.json"  # a published copy's signed manifest, kept beside its files


class ModelNotFound(LookupError):
    """The registry answered, but holds no model version under that name and alias."""


class CachedCopyRefused(store.RegistryUnreachable):
    """The registry cannot be used and the local copy fails its check (changed, damaged, or another
    model's): it is not run."""


def default_cache_dir() -> Path:
    """`$NEEDLECUE_MODEL_CACHE` if set, else `~/.cache/needlecue/models` (read at call time)."""
    env = os.environ.get(CACHE_ENV)
    return Path(env).expanduser() if env else DEFAULT_CACHE


def read_version(folder: Path) -> dict[str, Any] | None:
    """The folder's version.json, or None if it is missing or unreadable (then it is no usable copy)."""
    try:
        info = json.loads((folder / VERSION_FILE).read_text())
    except (OSError, ValueError):
        return None
    return info if isinstance(info, dict) else None


def is_copy_of(
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


@contextlib.contextmanager
def staging(target: Path, alias: str) -> Iterator[Path]:
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


def write_version(
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
