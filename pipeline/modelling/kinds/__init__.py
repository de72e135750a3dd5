"""The model kinds: one module each, one line each in `TABLE` (docs/model-kinds.md).

A kind is a `base.ModelKind`: its params section (a class in its module), its config, its training,
the inputs choice's stand-in for it, its runtime, and its label and colour in the report. Training,
prediction, export, calibration and the report ask the table (`kind_of(name)`, `kind_label(name)`)
and never branch on a kind's name. `vocab.KINDS` names the same kinds, simplest first, for
`config.py` (which the simulator's client loads, so it cannot import this table) to check the
params' kind names against when they are read; a test checks that the two agree.
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


def kind_label(name: str) -> str:
    """How the report names the kind called `name`: its label in the table, else the name in capitals."""
    kind = TABLE.get(name)
    return kind.label if kind is not None else name.upper()
