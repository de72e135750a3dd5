"""The cached copy when the registry or the bucket cannot be used: checked, then run with a warning
(an error when the source refused what it holds), or a clear error saying why not."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import needlecue_client.published as published
from needlecue_client.copies import VERSION_FILE, CachedCopyRefused
from needlecue_client.verify import Verify
from needlecue_runtime.registry import store

# One logger for the whole client, named as before it was split into modules (log configs keep working).
log = logging.getLogger("needlecue_client")


def offline_copy(
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
