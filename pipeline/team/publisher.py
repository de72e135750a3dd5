"""The lab's publisher: a small service beside the tracking server that keeps the published bucket up to
date (`pipeline.team.publish`), so that simulators never wait on the tracking server.

MLflow's registry webhook calls it on every alias change: the register stage's, `needlecue rollback`'s,
`needlecue calibrate`'s, or one made by hand in the MLflow UI. A verified call (signed with the stack's
webhook secret, fresh, not replayed: `needlecue_client.webhook.AliasListener`) wakes it, and it publishes
what is out of date of the models the calls named: idempotent, and a burst of calls (the register stage
moves one alias per angle) is one round. Every `interval_s` it publishes the whole registry, so that a
call MLflow could not deliver is caught.
The team stack runs it (`needlecue team start`); `python -m pipeline.team.publisher STACK_DIR` by hand.
"""

from __future__ import annotations

import logging
import sys
import threading
from pathlib import Path
from typing import Any

from needlecue_client.webhook import ALIAS_ENTITY, AliasListener
from pipeline.logs import setup
from pipeline.team import access, publish
from pipeline.team.stack import Stack

log = logging.getLogger(__name__)

INTERVAL_S = 60.0
WEBHOOK_NAME = "needlecue-publish"


class _Listener(AliasListener):
    """MLflow's alias webhook, verified as a simulator's listener verifies it (signature, age, replay),
    handing the publisher the model each call names (so a round publishes that model, not the whole
    registry)."""

    def __init__(self, publisher: Publisher, *args: Any) -> None:
        super().__init__(*args)
        self.publisher = publisher

    def handle(self, event: dict[str, Any]) -> int:
        data = event.get("data") or {}
        name = data.get("name")
        if event.get("entity") != ALIAS_ENTITY or not str(name).startswith(publish.MODEL_PREFIXES):
            return 0
        self.publisher.changed(str(name))
        log.info("webhook: %s@%s %s -> published at once", name, data.get("alias"), event.get("action"))
        return 1


class Publisher:
    """Publishes the stack's registry into its published bucket: the models webhook calls name, at
    once, and all of it every `interval_s`."""

    def __init__(self, stack: Stack, interval_s: float = INTERVAL_S) -> None:
        self.stack = stack
        self.interval_s = interval_s
        self._wake = threading.Event()
        self._lock = threading.Lock()
        self._named: set[str] = set()
        self.rounds = 0

    def changed(self, name: str) -> None:
        """An alias of `name` moved (a verified webhook call): publish it now."""
        with self._lock:
            self._named.add(name)
        self._wake.set()

    def once(self, names: set[str] | None = None) -> list[publish.Change]:
        """One round: bring the bucket up to date for `names` (all models: None), reading the registry
        as the lab."""
        target = publish.Target.of(self.stack, "publisher")
        with self.stack.as_lab():
            changes = publish.publish(self.stack.tracking_uri, target, names=names)
        self.rounds += 1
        return changes

    def serve(self, stop: threading.Event) -> None:
        """Listen for the webhook, register it with MLflow, and publish until `stop` is set."""
        settings = self.stack.settings
        listener = _Listener(self, settings["webhook_secret"], self.stack.host, self.stack.ports.publisher)
        with listener:
            access.ensure_webhook(self.stack, listener.url, WEBHOOK_NAME)
            log.info("listening at %s for MLflow's alias webhooks", listener.url)
            names: set[str] | None = None  # the first round publishes everything
            while not stop.is_set():
                try:
                    changes = self.once(names)
                    log.info("round %d (%s): %d change(s)", self.rounds,
                             "all" if names is None else ", ".join(sorted(names)), len(changes))  # fmt: skip
                except Exception as e:  # the next call or interval tries again; the service stays up
                    log.error("publishing failed (tried again at the next change or in %.0f s): %s: %s",
                              self.interval_s, type(e).__name__, e)  # fmt: skip
                woken = self._wake.wait(self.interval_s)
                self._wake.clear()
                with self._lock:
                    names, self._named = (set(self._named) if woken else None), set()


def main(argv: list[str]) -> None:
    setup("publisher")
    if len(argv) != 1:
        raise SystemExit("usage: python -m pipeline.team.publisher STACK_DIR")
    stack = Stack(Path(argv[0]))
    Publisher(stack, float(stack.settings.get("publish_every_s", INTERVAL_S))).serve(threading.Event())


if __name__ == "__main__":
    main(sys.argv[1:])
