"""Training one model of a kind (`pipeline.modelling.kinds`) for one insertion angle, on the
estimator's voltages only, into a self-describing checkpoint.

What a model reads (`x`) is its params' `inputs` (`needlecue_runtime.features`): raw volts as in
the paper, or the FSR conductance relative to the trial's rest reading, which transfers between
estimator units; the checkpoint records it.

How each kind trains is its own module's business (the networks standardise inputs and targets with
the training split's statistics only, and train bit for bit deterministically). torch is imported
inside the functions that need it.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import pandas as pd

from needlecue_runtime.features import inputs_for
from needlecue_runtime.frontend import Circuit
from needlecue_runtime.vocab import AXES, axes_of, channels_of, rate_hz
from pipeline.logs import Log
from pipeline.modelling.checkpoint import FORMAT, data_sha256
from pipeline.modelling.choice import Choice, choose_inputs
from pipeline.modelling.inputs import trial_codes
from pipeline.modelling.kinds import kind_of
from pipeline.modelling.kinds.base import KindParams
from pipeline.modelling.predictor import Predictor

LOSS_DEFINITION = "MSE of fx, fy, fz standardised by the training split's mean and std, averaged over axes"


def _angle_deg(frame: pd.DataFrame) -> float:
    if "angle_deg" not in frame.columns:
        return math.nan
    angles = pd.unique(frame["angle_deg"].dropna())
    if len(angles) != 1:
        raise ValueError(f"one model per angle: the training rows hold angles {sorted(angles)}")
    return float(angles[0])


@dataclass
class TrainResult:
    """What `fit` returns: the checkpoint dict, the per-epoch history and the summary metrics."""

    checkpoint: dict[str, Any]
    history: list[dict[str, float]]
    metrics: dict[str, Any]
    predictor: Predictor = field(init=False)

    def __post_init__(self) -> None:
        self.predictor = Predictor(self.checkpoint)


def fit(
    kind: str,
    params: KindParams,
    train: pd.DataFrame,
    val: pd.DataFrame | None = None,
    *,
    train_data_sha256: str | None = None,
    front_end: Circuit | None = None,
    other_designs: Sequence[str] = (),
    decided: Choice | None = None,
    log: Log | None = None,
) -> TrainResult:
    """Train one model of `kind` on `train`, early-stopping the networks on `val` (if it has rows).

    `train_data_sha256` identifies the data in the checkpoint; by default a hash of the frames.
    `front_end` is the circuit the training units declare, which the conductance inputs read through
    (ValueError if they need one and there is none); `other_designs`, the units the model must also
    serve that declare another circuit (then `inputs.kind: auto` chooses among the conductance kinds).
    With `inputs.kind: auto` each candidate is scored on this angle's rows, and the best is trained,
    or the kind `decided` for all the model kind's angles (the choose stage's), with this angle's
    scores beside it.
    """
    model_kind = kind_of(kind, "train")
    if not isinstance(params, model_kind.params):
        raise TypeError(f"{kind} takes {model_kind.params.__name__}, got {type(params).__name__}")
    if train.empty:
        raise ValueError("no training rows")
    val = train.iloc[:0] if val is None else val
    channels = channels_of(train)
    if not channels:
        raise ValueError(f"the training rows have no estimator channel (columns: {list(train.columns)})")
    targets = axes_of(train.columns)  # the forces its reference recorded (reference.axes)
    if not targets:
        raise ValueError(
            f"the training rows have no force column of {list(AXES)} (columns: {list(train.columns)})"
        )
    if not val.empty and axes_of(val.columns) != targets:
        raise ValueError(
            f"validation forces {list(axes_of(val.columns))} differ from training forces {list(targets)}"
        )
    if not val.empty and channels_of(val) != channels:
        raise ValueError(f"validation channels {channels_of(val)} differ from training channels {channels}")

    log = log or (lambda _msg: None)
    model_kind.import_backends()  # before the clock: train_seconds measures the work, not the imports
    codes = trial_codes(train)
    started = time.perf_counter()
    choice = None
    if params.inputs.kind == "auto":  # chosen by validation on this data (pipeline.modelling.choice)
        choice = choose(kind, params, train, val, front_end, other_designs)
        if decided is not None:  # one kind for all angles: this angle's own scores stay beside it
            choice = replace(choice, chosen=decided.chosen, folds=decided.folds)
    if choice is not None:
        only = f", among {choice.only}" if choice.only else ""
        log(f"inputs by validation ({choice.folds}{only}): {choice.chosen}; mean NRMSE % {choice.scores}")
    elif other_designs and front_end is not None and not params.inputs.kind.endswith("conductance"):
        who = ", ".join(other_designs)
        log(f"warning: {who}: another circuit declared, which {params.inputs.kind} inputs cannot read")
    spec = inputs_for(choice.chosen if choice else params.inputs.kind, params.inputs.rest_s, front_end)
    cfg = replace(model_kind.config(params, len(channels)), n_out=len(targets))
    state, pre, history, summary = model_kind.train(cfg, params, spec, train, val, channels, log)

    seconds = time.perf_counter() - started
    sha = train_data_sha256 or data_sha256(train, val)
    checkpoint = {
        "format": FORMAT,
        "kind": kind,
        "config": cfg.to_dict(),
        "state_dict": state,
        "preprocessing": pre,
        "channels": list(channels),
        "inputs": spec.model_dump(mode="json"),
        "inputs_choice": None if choice is None else choice.to_dict(),  # None: pinned in params
        "targets": list(targets),
        "rate_hz": rate_hz(train["t_s"], codes) if "t_s" in train.columns else math.nan,
        "angle_deg": _angle_deg(train),
        "train_data_sha256": sha,
        "params": params.model_dump(mode="json"),
        "torch_version": _torch_version(),
    }
    metrics = {
        "kind": kind,
        "angle_deg": checkpoint["angle_deg"],
        **summary,
        "loss": LOSS_DEFINITION,
        "inputs": spec.kind,
        "inputs_choice": None if choice is None else choice.to_dict(),
        "train_seconds": round(seconds, 3),
        "n_train": len(train),
        "n_val": len(val),
        "train_data_sha256": sha,
    }
    return TrainResult(checkpoint, history, metrics)


def choose(
    kind: str,
    params: KindParams,
    train: pd.DataFrame,
    val: pd.DataFrame,
    front_end: Circuit | None,
    other_designs: Sequence[str] = (),
) -> Choice:
    """`choose_inputs` for one angle's rows with the kind's own stand-in (e.g. the LSTM's window,
    least squares' intercept)."""
    stand_in = kind_of(kind, "choose the inputs of").stand_in(params)
    rest_s, channels = params.inputs.rest_s, channels_of(train)
    return choose_inputs(stand_in, train, val, channels, front_end, rest_s, other_designs)


def _torch_version() -> str:
    import torch

    return str(torch.__version__)
