"""Force against the training insertions per angle, per model kind the stage passes: the kind itself
where its inputs-choice stand-in is linear (LS), else the networks' stand-in (the ridge regression that
`pipeline.modelling.choice` scores inputs with: the kind's `stand_in`), refitted per angle on a
subsample and scored on that angle's external trials of the training units, NRMSE % (eq. 3-4). Not
the trained networks: an LSTM per subsample would cost minutes each."""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from needlecue_runtime.features import inputs_for
from needlecue_runtime.frontend import Circuit
from needlecue_runtime.vocab import angle_name, axes_of, channels_of
from pipeline.dataset.splits import common_front_end
from pipeline.logs import Log
from pipeline.metrics.scores import mean_known, nrmse_pct
from pipeline.modelling.choice import load_choice, ridge, stand_in_basis  # the stand-in as choose scores
from pipeline.modelling.fit import fit
from pipeline.modelling.inputs import features_of, times_of, trial_codes
from pipeline.modelling.kinds import kind_label, kind_of
from pipeline.modelling.kinds.base import StandIn
from pipeline.needs.document import force_name, networks
from pipeline.needs.subsample import Selection, select


@dataclass(frozen=True)
class ForceModel:
    """A force model refitted per angle: `predict(training rows, rows)` gives forces (n, 3) on rows."""

    about: str
    predict: Callable[[pd.DataFrame, pd.DataFrame], np.ndarray]


def chosen_kind(model: str, section: Any, choices_dir: Path) -> str:
    """The inputs the train stage gives `model`: pinned in params, else the choose stage's decision
    (ValueError naming the file when there is none)."""
    if section.inputs.kind != "auto":
        return section.inputs.kind
    path = Path(choices_dir) / f"{model}.json"
    if not path.is_file():
        raise ValueError(f"{path}: missing (run the choose stage)")
    choice = load_choice(path, model)
    if choice is None:
        raise ValueError(f"{path} was written with the inputs pinned; params.yaml now says auto (run choose)")
    return choice.chosen


def fitted_model(kind: str, params: Any, inputs: str, front_end: Circuit | None) -> ForceModel:
    """The model `kind` itself (one whose stand-in is linear: least squares, the paper's calibration
    matrix) on the inputs `inputs`, as the train stage fits it."""
    inputs_for(inputs, params.inputs.rest_s, front_end)  # a kind needing an undeclared circuit fails here
    pinned = params.model_copy(update={"inputs": params.inputs.model_copy(update={"kind": inputs})})

    def predict(train: pd.DataFrame, rows: pd.DataFrame) -> np.ndarray:
        found = fit(kind, pinned, train, train_data_sha256="subsample", front_end=front_end)
        return found.predictor.predict(rows.drop(columns=list(axes_of(rows.columns))))

    return ForceModel(f"{kind_label(kind)} (the paper's calibration matrix) on {inputs}", predict)


def stand_in_model(
    kind: str, stand_in: StandIn, params: Any, inputs: str, front_end: Circuit | None, others: str
) -> ForceModel:
    """The networks' stand-in of the inputs choice for `kind` (`stand_in`): ridge on its inputs, their
    squares and pairwise products (and lags, for a kind with memory). Not a trained network (`others`:
    the kinds it is not, in words)."""
    spec = inputs_for(inputs, params.inputs.rest_s, front_end)

    def predict(train: pd.DataFrame, rows: pd.DataFrame) -> np.ndarray:
        # one basis over both, standardised over both, as the inputs choice builds it for its folds
        both = pd.concat([train, rows.drop(columns=list(axes_of(rows.columns)))], ignore_index=True)
        x = features_of(both, channels_of(train), spec)
        basis = stand_in_basis(
            x, stand_in.linear, stand_in.intercept, list(stand_in.lags), trial_codes(both), times_of(both)
        )
        weights = ridge(basis[: len(train)], train[list(axes_of(train.columns))].to_numpy(np.float64))
        return basis[len(train) :] @ weights

    lags = f", lags {list(stand_in.lags)} samples" if stand_in.lags else ""
    about = (
        f"the networks' stand-in (ridge on the {kind_label(kind)}'s inputs {inputs}, their squares and "
        f"pairwise products{lags})"
    )
    return ForceModel(f"{about}, not a trained {others}", predict)


def force_models(
    kinds: Sequence[tuple[str, Any]],
    choices_dir: Path,
    circuits: Mapping[str, Circuit | None],
    units: Sequence[str],
) -> tuple[dict[str, ForceModel], list[dict[str, str]]]:
    """Per model kind of `kinds` ((kind, its params section)), in order: the kind itself where its
    inputs-choice stand-in is linear (the model is), else the networks' stand-in, named by
    `pipeline.needs.document.force_name`; on the inputs the train stage gives the kind, read through
    the circuit the training `units` share. What cannot be built is said instead."""
    try:
        front_end = common_front_end(dict(circuits), units)
    except ValueError as e:
        return {}, [{"what": "force against training insertions", "why": str(e)}]
    stand_ins = [(kind, params, kind_of(kind, "refit").stand_in(params)) for kind, params in kinds]
    others = networks(kind for kind, _, s in stand_ins if s.linear)
    models, notes = {}, []
    for kind, params, s in stand_ins:
        name = force_name(kind, not s.linear)
        try:
            inputs = chosen_kind(kind, params, choices_dir)
            if s.linear:
                models[name] = fitted_model(kind, params, inputs, front_end)
            else:
                models[name] = stand_in_model(kind, s, params, inputs, front_end, others)
        except ValueError as e:
            notes.append({"what": f"force of {name}", "why": str(e)})
    return models, notes


def _pct(x: float | None) -> str:
    return "unknown" if x is None else f"{x:.2f} %"


def force_curve(
    train: Mapping[float, pd.DataFrame],
    same: Mapping[float, pd.DataFrame],
    selections: Sequence[Selection],
    models: Mapping[str, ForceModel],
    log: Log,
) -> tuple[list[dict[str, Any]], list[dict[str, str]]]:
    """Per selection, {model: {"mean_nrmse_pct", "by_angle"}}: each model fitted on every angle's
    selected training trials and scored on that angle's rows in `same`; and what could not be."""
    steps: list[dict[str, Any]] = [{} for _ in selections]
    if not same:
        return steps, [
            {"what": "force against training insertions", "why": "no external trial of a training unit"}
        ]
    notes = []
    for name, model in models.items():
        try:
            for step, sel in zip(steps, selections, strict=True):
                by_angle = {}
                for a in sorted(set(sel) & set(same)):
                    pred = model.predict(select(train[a], sel[a]), same[a])
                    truth = same[a][list(axes_of(train[a].columns))]  # the forces the model estimates
                    by_angle[angle_name(a)] = mean_known(nrmse_pct(pred, truth).tolist())
                step[name] = {"mean_nrmse_pct": mean_known(by_angle.values()), "by_angle": by_angle}
        except ValueError as e:  # the data cannot be read the way the model reads it
            notes.append({"what": f"force of {name}", "why": str(e)})
            for step in steps:
                step.pop(name, None)
    for step, sel in zip(steps, selections, strict=True):
        figures = ", ".join(f"{name} {_pct(f['mean_nrmse_pct'])}" for name, f in step.items())
        log(f"force with {max(map(len, sel.values()))} training insertions per angle: {figures or 'none'}")
    return steps, notes
