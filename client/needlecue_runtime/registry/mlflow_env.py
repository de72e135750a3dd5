"""MLflow's process-wide settings for one block, restored after it: its HTTP patience, any environment
variables, and the store its fluent API uses. Shared by the `register` stage, the simulator's client,
the team stack and the `needlecue` commands; mlflow is imported inside `fluent` only, so importing this
module is cheap."""

from __future__ import annotations

import os
import threading
from collections.abc import Iterator
from contextlib import contextmanager

# Fail fast on an unreachable HTTP store instead of MLflow's default minutes of retries (`patience`).
HTTP_SETTINGS = {"MLFLOW_HTTP_REQUEST_MAX_RETRIES": "0", "MLFLOW_HTTP_REQUEST_TIMEOUT": "10"}
# A writer waits longer for each answer: a server busy with many clients can take over 10 s for one
# request (seen in CI, just after a restart), and a register given up half way has to be run again.
# An unreachable server still fails at once: no retries.
WRITE_TIMEOUT_S = "60"


@contextmanager
def patience(write: bool = False) -> Iterator[None]:
    """MLflow's HTTP settings for the block, restored after it: no retries and 10 s per answer (60 s
    for a writer), each unless the environment sets it. MLflow reads them from the environment at
    every request; there is no per-client setting."""
    wanted = {**HTTP_SETTINGS, **({"MLFLOW_HTTP_REQUEST_TIMEOUT": WRITE_TIMEOUT_S} if write else {})}
    with environment({k: _outer_value(k) or v for k, v in wanted.items()}):
        yield


# The blocks of `environment` now open, per variable: [(None, its value before the first), (block, its
# value), ...]. The environment is the process's, shared by every thread (clients polling on threads).
_ENV_LOCK = threading.Lock()
_ENV_BLOCKS: dict[str, list[tuple[object, str | None]]] = {}


def _outer_value(key: str) -> str | None:
    """The variable's value outside every open `environment` block: what the user's environment sets."""
    with _ENV_LOCK:
        blocks = _ENV_BLOCKS.get(key)
        return blocks[0][1] if blocks else os.environ.get(key)


def _set_env(key: str, value: str | None) -> None:
    if value:
        os.environ[key] = value
    else:
        os.environ.pop(key, None)


@contextmanager
def environment(values: dict[str, str]) -> Iterator[None]:
    """Set environment variables for the block; each restored (or removed) after it. An empty value
    is a variable that is not set. Blocks may overlap on several threads and end in any order: when
    one ends, a variable takes the value of the latest block still open, or, when none is, its value
    from before the first (two polls on two threads, each restoring what it saw, once left the other's
    2 s timeout in the process for good)."""
    block = object()
    with _ENV_LOCK:
        for key, value in values.items():
            _ENV_BLOCKS.setdefault(key, [(None, os.environ.get(key))]).append((block, value or None))
            _set_env(key, value)
    try:
        yield
    finally:
        with _ENV_LOCK:
            for key in values:
                blocks = [b for b in _ENV_BLOCKS[key] if b[0] is not block]
                _set_env(key, blocks[-1][1])
                if len(blocks) > 1:
                    _ENV_BLOCKS[key] = blocks
                else:
                    del _ENV_BLOCKS[key]


@contextmanager
def fluent(uri: str) -> Iterator[None]:
    """MLflow's fluent API (`mlflow.start_run`, `mlflow.register_model`, `models:/` downloads) on the
    store at `uri`, tracking and registry, for the block. After it, MLflow's process-wide URIs and the
    environment variables `set_tracking_uri` writes are as they were, and MLflow reads its URIs from
    them again (public API only: `set_tracking_uri` writes the environment variable whenever it sets
    a URI, so a URI set before the block is in the environment the block restores)."""
    import mlflow

    with environment({k: os.environ.get(k, "") for k in ("MLFLOW_TRACKING_URI", "MLFLOW_REGISTRY_URI")}):
        mlflow.set_tracking_uri(uri)
        mlflow.set_registry_uri(uri)
        try:
            yield
        finally:  # unset: MLflow falls back to the environment, restored as the block ends
            mlflow.set_tracking_uri(None)
            mlflow.set_registry_uri(None)
