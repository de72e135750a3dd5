"""Following an alias: when a client made by `ForceClient.from_registry` asks the registry where its
alias points (at most once every `poll_s` seconds, at once after a webhook), what it found, and the
version it refused; the client swaps its one `Model` reference when the alias moved."""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from needlecue_client.cache import fetch, poll_alias, source_uri
from needlecue_client.copies import default_cache_dir
from needlecue_client.model import Model
from needlecue_runtime.registry import store

log = logging.getLogger("needlecue_client")


def _monotonic() -> float:
    """The clock of the alias polls (a function of its own, so that tests can move it)."""
    return time.monotonic()


@dataclass
class Follower:
    """How a registry client was fetched, and when it next asks the registry where its alias points."""

    angle_deg: float
    alias: str
    fetch_kwargs: dict[str, Any]  # cache_dir and tracking_uri, fixed when the client was made
    poll_s: float | None
    next_poll: float  # on the `_monotonic` clock; inf: no automatic polls
    refused: tuple[str, Any] | None = None  # (version, source) refused: not tried again until the alias moves
    failing: bool = False  # the last poll could not reach the registry (it was warned about once)

    @classmethod
    def start(
        cls, angle_deg: float, alias: str, fetch_kwargs: dict[str, Any], poll_s: float | None
    ) -> Follower:
        """A follower of `models:/needle-force-<angle>@<alias>` in the store and cache of `fetch_kwargs`
        (`tracking_uri`, `cache_dir`: the defaults are read now)."""
        if poll_s is not None and not poll_s >= 0:
            raise ValueError(f"poll_s is seconds >= 0 or None, got {poll_s!r}")
        kwargs = dict(fetch_kwargs)
        kwargs["tracking_uri"] = source_uri(kwargs.get("tracking_uri"))  # or the published bucket
        kwargs["cache_dir"] = Path(kwargs.get("cache_dir") or default_cache_dir()).expanduser()
        return cls(angle_deg, alias, kwargs, poll_s or None, _monotonic() + poll_s if poll_s else math.inf)

    @property
    def model_name(self) -> str:
        return store.model_name(self.angle_deg)

    def due(self) -> bool:
        """Whether `poll_s` has passed since the last poll (or a webhook asked for one)."""
        return _monotonic() >= self.next_poll

    def polled(self) -> None:
        """A poll starts now: the next one is due `poll_s` later."""
        self.next_poll = _monotonic() + self.poll_s if self.poll_s else math.inf

    def poll_soon(self) -> None:
        self.next_poll = -math.inf

    def where(self) -> tuple[str, Any]:
        """(version, source) the alias points to now: one quick metadata request (no retries, short
        timeout). `RegistryUnreachable` or `ModelNotFound` as `fetch` raises them."""
        mv = poll_alias(self.model_name, self.alias, self.fetch_kwargs["tracking_uri"])
        if self.failing:
            log.info("%s@%s: the registry answers again", self.model_name, self.alias)
            self.failing = False
        return str(mv.version), mv.source

    def fetch(self) -> Model:
        """The model the alias points to, fetched (or the cached copy) and opened."""
        return Model.open(fetch(self.angle_deg, self.alias, **self.fetch_kwargs))

    def failed(self, error: Exception, keeping: str) -> None:
        """The registry could not be asked: warned once until a poll succeeds again."""
        when = f"next try in {self.poll_s:g} s" if self.poll_s else "no automatic polls"
        level = logging.DEBUG if self.failing else logging.WARNING
        log.log(
            level,
            "%s@%s: cannot poll the registry (%s); keeping %s, %s",
            self.model_name,
            self.alias,
            error,
            keeping,
            when,
        )
        self.failing = True
