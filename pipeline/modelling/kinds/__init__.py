"""The model kinds: one module each, one line each in `TABLE` (docs/model-kinds.md).

A kind is a `base.ModelKind`: its params section, its config, its training, the inputs choice's
stand-in for it and its runtime. Training, prediction, export and calibration ask `kind_of(name)`
and never branch on a kind's name; `vocab.KINDS` names the same kinds, simplest first, for the
params (a test checks the two agree).
"""

from __future__ import annotations

from pipeline.modelling.kinds.base import ModelKind
from pipeline.modelling.kinds.fnn import FNN
from pipeline.modelling.kinds.ls import LS
from pipeline.modelling.kinds.lstm import LSTM

TABLE: dict[str, ModelKind] = {kind.name: kind for kind in (LS(), FNN(), LSTM())}


def kind_of(name: str, what: str = "use") -> ModelKind:
    """The kind called `name`; ValueError saying what could not be done with it otherwise."""
    try:
        return TABLE[name]
    except (KeyError, TypeError):
        raise ValueError(f"cannot {what} model kind {name!r}; expected one of {', '.join(TABLE)}") from None
