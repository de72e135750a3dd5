"""Fixtures of the client's tests: a registered LSTM with its cue pack, its fetched folder, tiny LS
models, and hand-moved poll clock and counted registry connections."""

from __future__ import annotations

from pathlib import Path

import pandas as pd
import pytest

from needlecue_client import fetch, follow
from needlecue_runtime.registry import store
from needlecue_runtime.vocab import AXES
from pipeline.config import CuesParams
from pipeline.cues.packs import build_cue_pack
from pipeline.modelling.fit import fit
from tests.client.builders import TINY, Clock, Registered, cue_predictions, cue_trials, register
from tests.projects import new_store


@pytest.fixture(scope="package")
def registered(empty_store: Path, tmp_path_factory: pytest.TempPathFactory) -> Registered:
    """A tiny 30° LSTM and its cue pack (from four angles' training trials), registered once for the
    client's tests in a store of its own."""
    root = tmp_path_factory.mktemp("registry")
    uri = new_store(empty_store, root)
    train = {a: cue_trials(a, 3, "b1") for a in (0, 15, 30, 45)}
    train = {a: pd.concat([f, cue_trials(a, 3, "b2", seed=1)], ignore_index=True) for a, f in train.items()}
    checkpoint = fit("lstm", TINY["lstm"], train[30]).checkpoint
    pack = build_cue_pack(train, 30, CuesParams(), cue_predictions(checkpoint, train))
    register(uri, root, checkpoint, pack)
    return Registered(uri, checkpoint, pack)


@pytest.fixture(scope="package")
def fetched(registered: Registered, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The registered model fetched once into a cache of its own (read-only for the tests)."""
    return fetch(30, cache_dir=tmp_path_factory.mktemp("cache"), tracking_uri=registered.uri)


@pytest.fixture
def clock(monkeypatch: pytest.MonkeyPatch) -> Clock:
    c = Clock()
    monkeypatch.setattr(follow, "_monotonic", c)
    return c


@pytest.fixture
def registry_calls(monkeypatch: pytest.MonkeyPatch) -> list[str | None]:
    """The store of every store.connect (a poll, or a fetch), in order."""
    calls: list[str | None] = []
    real = store.connect

    def counting(uri: str | None = None, **kwargs: bool) -> object:
        calls.append(uri)
        return real(uri, **kwargs)

    monkeypatch.setattr(store, "connect", counting)
    return calls


@pytest.fixture(scope="package")
def ls_models() -> dict[str, dict]:
    """Tiny 30° LS checkpoints: `a`, `b` (trained on doubled forces: other predictions) and `fsr4` (reads
    fsr1, fsr2, fsr4 instead of fsr3)."""
    train = cue_trials(30, 2)
    doubled = train.assign(**{c: 2 * train[c] for c in AXES})
    return {
        "a": fit("ls", TINY["ls"], train).checkpoint,
        "b": fit("ls", TINY["ls"], doubled).checkpoint,
        "fsr4": fit("ls", TINY["ls"], train.rename(columns={"fsr3": "fsr4"})).checkpoint,
    }
