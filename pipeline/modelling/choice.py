"""Choosing a model's inputs by validation on the lab's own data (`<model>.inputs.kind: auto`).

Which inputs carry the force best depends on the rig: the volts of one circuit are nearly linear in
the load, another's saturate; a rest-relative reading removes a preload some rigs do not have. A lab
cannot be expected to know which, so each candidate kind (`features.INPUT_KINDS`; the conductance kinds
only where the training units declare their circuit) is scored on held-out data, and the best is
trained. Training the network once per candidate would cost several times the training; a fixed
stand-in costs a few linear solves, and each model kind says which (`StandIn`, from its module in
`pipeline.modelling.kinds`): for least squares the model itself (linear in the inputs), for the
networks a ridge regression on each input, its square and the pairwise products (a smooth map of
the inputs, as a small network fits), plus, for the LSTM, the inputs a quarter and a half of its
window back (its memory). The folds:

- leave-one-unit-out when the training rows come from several estimator units: what a new unit
  will meet, and where a unit-specific preload or gain hurts;
- else by trial: fitted on the train split, scored on the validation split (5 folds by trial when
  that is empty).

The score is the mean over folds of the NRMSE (% of each axis' range, mean of fx, fy, fz). Ties go
to the simpler kind (the order of `INPUT_KINDS`). A model kind has one choice for all its angles (`pool`:
each candidate's score averaged over the angles): per angle, the choice flips between near-tied kinds,
while a unit's calibration transform is one for all angles' models. Pure numpy.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from needlecue_runtime.features import INPUT_KINDS, ModelInputs
from needlecue_runtime.frontend import Circuit
from needlecue_runtime.vocab import axes_of
from pipeline.modelling.inputs import features_of, sequence_order, times_of, trial_codes
from pipeline.modelling.kinds.base import StandIn

FORMAT = "needlecue-inputs-choice/1"  # the choose stage's file: one model kind's choice
RIDGE = 1e-3  # relative to the mean diagonal of the normal equations: only against ill-conditioning
MIN_FOLD_ROWS = 20  # a fold with fewer held-out rows is not scored


@dataclass(frozen=True)
class Choice:
    """The inputs chosen for one model, and why: each candidate's score (mean NRMSE %, None where it
    could not be computed), the folds and the stand-in model."""

    chosen: str
    scores: dict[str, float | None]
    folds: str
    stand_in: str
    only: str | None = None  # why some kinds were not candidates (None: every kind the data allows)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def candidates(front_end: Circuit | None, other_designs: Sequence[str] = ()) -> list[str]:
    """The input kinds a model can read: the conductance kinds only through a declared circuit, and
    only they when it must also serve units that declare another circuit (`other_designs`): the
    volts of one design are not the volts of another, the FSR's conductance is."""
    if front_end is None:
        return [k for k in INPUT_KINDS if not k.endswith("conductance")]
    return [k for k in INPUT_KINDS if k.endswith("conductance") or not other_designs]


def stand_in_basis(
    x: np.ndarray, linear: bool, intercept: bool, lags: Sequence[int], codes: np.ndarray, t: np.ndarray
) -> np.ndarray:
    """The inputs as they are (`linear`, least squares), or standardised with their squares and
    pairwise products, and the lagged inputs; a column of ones with `intercept`."""
    ones = [np.ones((len(x), 1))] if intercept else []
    if linear:
        return np.concatenate([*ones, x], axis=1)
    mean, std = x.mean(axis=0), x.std(axis=0)
    z = (x - mean) / np.where(std > 0, std, 1.0)
    cols = [z, z**2]
    c = z.shape[1]
    cols += [z[:, [i]] * z[:, [j]] for i in range(c) for j in range(i + 1, c)]
    if lags:
        order, start = sequence_order(codes, t)
        pos = np.empty(len(order), dtype=np.int64)
        pos[order] = np.arange(len(order))
        for lag in lags:  # the row `lag` samples back in its own trial (its first row at the start)
            back = order[np.maximum(pos - lag, start[pos])]
            cols.append(z[back])
    return np.concatenate([*ones, *cols], axis=1)


def _nrmse(pred: np.ndarray, y: np.ndarray) -> float:
    span = y.max(axis=0) - y.min(axis=0)
    rmse = np.sqrt(np.mean((pred - y) ** 2, axis=0))
    return float(np.mean(100.0 * rmse / np.where(span > 0, span, 1.0)))


def ridge(a: np.ndarray, y: np.ndarray) -> np.ndarray:
    gram = a.T @ a
    lam = RIDGE * float(np.trace(gram)) / len(gram) if len(gram) else 0.0
    return np.linalg.solve(gram + lam * np.eye(len(gram)), a.T @ y)


def _folds(
    train: pd.DataFrame, val: pd.DataFrame
) -> tuple[str, list[tuple[np.ndarray, np.ndarray]], pd.DataFrame]:
    """(description, [(fit rows, score rows)], the rows they index)."""
    rows = pd.concat([train, val], ignore_index=True) if len(val) else train.reset_index(drop=True)
    units = rows["unit_id"].astype(str).to_numpy() if "unit_id" in rows.columns else np.full(len(rows), "")
    distinct = sorted(set(units))
    if len(distinct) >= 2:
        folds = [(units != u, units == u) for u in distinct]
        return f"leave-one-unit-out ({len(distinct)} units)", folds, rows
    if len(val):
        is_val = np.r_[np.zeros(len(train), bool), np.ones(len(val), bool)]
        return "by trial: train split -> validation split", [(~is_val, is_val)], rows
    codes = trial_codes(rows)
    fold = codes % 5
    return "by trial: 5 folds", [(fold != k, fold == k) for k in range(5)], rows


def choose_inputs(
    stand_in: StandIn,
    train: pd.DataFrame,
    val: pd.DataFrame,
    channels: list[str],
    front_end: Circuit | None,
    rest_s: float,
    other_designs: Sequence[str] = (),
) -> Choice:
    """The input kind that `stand_in` predicts the force from best on held-out rows (module
    docstring), among `candidates(front_end, other_designs)`."""
    folds_txt, folds, rows = _folds(train, val)
    y = rows[list(axes_of(rows.columns))].to_numpy(np.float64)
    codes, t = trial_codes(rows), times_of(rows)
    scores: dict[str, float | None] = {}
    kinds = candidates(front_end, other_designs)
    for kind in kinds:
        spec = ModelInputs(
            kind=kind, rest_s=rest_s, front_end=front_end if kind.endswith("conductance") else None
        )
        x = features_of(rows, channels, spec)
        a = stand_in_basis(x, stand_in.linear, stand_in.intercept, stand_in.lags, codes, t)
        found = []
        for fit_rows, score_rows in folds:
            if score_rows.sum() < MIN_FOLD_ROWS or fit_rows.sum() <= a.shape[1]:
                continue
            w = ridge(a[fit_rows], y[fit_rows])
            found.append(_nrmse(a[score_rows] @ w, y[score_rows]))
        scores[kind] = float(np.mean(found)) if found else None
    known = {k: s for k, s in scores.items() if s is not None and np.isfinite(s)}
    chosen = min(known, key=lambda k: (round(known[k], 6), INPUT_KINDS.index(k))) if known else kinds[0]
    only = None
    if front_end is not None and other_designs:
        verb = "declares" if len(other_designs) == 1 else "declare"
        only = f"the conductance kinds: {', '.join(other_designs)} {verb} another circuit"
    return Choice(
        chosen,
        {k: None if s is None else round(s, 4) for k, s in scores.items()},
        folds_txt,
        stand_in.describe(),
        only,
    )


def pool(by_angle: Mapping[str, Choice]) -> Choice:
    """One choice over all angles of a model kind (`{angle name: that angle's choice}`): each kind
    that was a candidate at every angle, scored by its mean over the angles where it was scored."""
    if not by_angle:
        raise ValueError("no angle to choose the inputs on")
    choices = list(by_angle.values())
    kinds = [k for k in choices[0].scores if all(k in c.scores for c in choices)]
    if not kinds:
        raise ValueError(
            "no input kind is a candidate at every angle: "
            + "; ".join(f"{a}°: {', '.join(c.scores)}" for a, c in by_angle.items())
        )
    scores: dict[str, float | None] = {}
    for kind in kinds:
        found = [s for c in choices if (s := c.scores[kind]) is not None and np.isfinite(s)]
        scores[kind] = round(float(np.mean(found)), 4) if found else None
    known = {k: s for k, s in scores.items() if s is not None}
    chosen = min(known, key=lambda k: (known[k], INPUT_KINDS.index(k))) if known else kinds[0]
    folds = sorted({c.folds for c in choices})
    where = f"at each of {len(choices)} angles, scores averaged" if len(choices) > 1 else "at one angle"
    return replace(
        choices[0],
        chosen=chosen,
        scores=scores,
        folds=f"{'; '.join(folds)}, {where}",
        only="; ".join(sorted({c.only for c in choices if c.only})) or None,
    )


def save_choice(path: Path, kind: str, choice: Choice | None, pinned: str | None = None) -> None:
    """The choose stage's file: `kind`'s decision for all its angles (the kind, the folds, the
    stand-in; not the scores, so that new data at one angle changes the file, and retrains the
    other angles, only when it changes the decision), or the kind `pinned` in params."""
    path.parent.mkdir(parents=True, exist_ok=True)
    found = None if choice is None else {k: v for k, v in choice.to_dict().items() if k != "scores"}
    doc = {"format": FORMAT, "model": kind, "pinned": pinned, "choice": found}
    path.write_text(json.dumps(doc, indent=2) + "\n")


def load_choice(path: Path, kind: str) -> Choice | None:
    """The decision `save_choice` wrote for `kind` (no scores; None: pinned in params); ValueError
    naming the file when it is not one, or is another model kind's."""
    try:
        doc = json.loads(path.read_text())
        found = (doc["format"], doc["model"], doc["choice"])
        choice = None if found[2] is None else Choice(**{**found[2], "scores": {}})
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise ValueError(f"{path}: not a readable inputs choice ({e}); run the choose stage") from e
    if found[:2] != (FORMAT, kind):
        raise ValueError(f"{path}: {found[:2]} is not {kind}'s inputs choice ({FORMAT}); run choose")
    return choice
