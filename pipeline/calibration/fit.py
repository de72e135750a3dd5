"""Fitting one unit's transform through frozen models, such that each shared model, reading the
unit through it, gives the reference force of the unit's calibration trials at its angle. Where the
unit declares its circuit the map acts on the FSRs' conductance, g' = g A^T + b, before the model's
inputs are computed from it (the part-to-part quantity: a unit's FSR gains scale its conductance,
whatever inputs the model reads); otherwise on the model's inputs, x' = x A^T + b
(`needlecue_runtime.features.InputTransform`).

One transform per unit and model kind, shared by the angles: what differs between units (FSR gain,
placement, alignment) belongs to the unit, not to the angle, so every calibration insertion constrains
the same few numbers and angles without a calibration insertion are calibrated too. The loss is the
mean squared force error in newtons, divided per angle by the reference force's spread pooled over the
three axes (`force_scale`), plus `ridge` times
the squared distance from the identity. Full-batch L-BFGS in float64 on one thread: the same data
give the same transform bit for bit. If the fit does not lower the loss, the identity is kept.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd

from needlecue_runtime.features import MIN_CONDUCTANCE_US, NEEDS_CIRCUIT, InputTransform, rest_reading
from needlecue_runtime.frontend import Circuit, conductance_us, volts_of_conductance
from needlecue_runtime.vocab import AXES, axes_of
from pipeline.config import CalibrateParams
from pipeline.execution.workers import ordered_map, workers_for
from pipeline.modelling.determinism import deterministic_torch, exact_lbfgs
from pipeline.modelling.inputs import features_of, sequence_order, times_of, trial_codes, window_index
from pipeline.modelling.predictor import Predictor

WORTH_A_WORKER = 200_000  # rows through the models over all fits (fewer fit faster than a worker starts)
MIN_FORCE_STD = 1e-3  # N: a flat reference force would otherwise weigh without bound


def force_scale(y: np.ndarray) -> float:
    """One angle's force spread (N): the root mean of the three axes' variances, floored.

    One number for the three axes, not one per axis: an axis that hardly moves at an angle (the
    lateral axes of a vertical insertion, whose spread in one trial is mostly the reference's noise)
    would otherwise weigh as much as the axis that carries the force, and the fit would bend the
    unit's transform to match noise (docs/units.md)."""
    return max(float(np.sqrt(np.mean(y.var(axis=0)))), MIN_FORCE_STD)


@dataclass(frozen=True)
class AngleData:
    """One angle's calibration rows as a frozen model reads them, in trial-time order: what the unit's
    map acts on (`x`), and, in the conductance domain, how the model's inputs follow from it."""

    predictor: Predictor
    x: np.ndarray  # (n, c) the FSRs' conductance (µS; the unit declares its circuit), else the model's inputs
    y: np.ndarray  # (n, len(axes)) reference force, N
    windows: np.ndarray | None  # (n, window) row positions of each row's LSTM window, or None
    front_end: Circuit | None = None  # the unit's circuit: the map acts on conductance
    rest: np.ndarray | None = None  # (n, c) per row, the conductance of its rest reading (raw volts)
    axes: tuple[str, ...] = AXES  # the forces the calibration's reference recorded (of the model's targets)

    @property
    def columns(self) -> list[int] | None:
        """The model's output columns the reference recorded; None: all of them, in order."""
        targets = list(self.predictor.targets)
        return None if list(self.axes) == targets else [targets.index(a) for a in self.axes]

    @property
    def domain(self) -> str:
        return "inputs" if self.front_end is None else "conductance"

    @classmethod
    def of(cls, predictor: Predictor, frame: pd.DataFrame, front_end: Circuit | None = None) -> AngleData:
        """The rows as the model reads them; with the unit's declared circuit, its FSRs' conductance
        through it, the map's domain."""
        codes, t = trial_codes(frame), times_of(frame)
        order, start = sequence_order(codes, t)
        axes = tuple(a for a in axes_of(frame.columns) if a in predictor.targets)
        if not axes:
            raise ValueError(
                f"the calibration rows record none of the forces {list(predictor.targets)} it estimates"
            )
        y = frame[list(axes)].to_numpy(np.float64)[order]
        windows = window_index(start, predictor.window) if predictor.sequence else None
        if front_end is None:
            x = features_of(frame, list(predictor.channels), predictor.inputs)[order]
            return cls(predictor, x, y, windows, axes=axes)
        volts = frame[list(predictor.channels)].to_numpy(np.float64)[order]
        rest = None
        if predictor.inputs.kind.startswith("rest_"):  # the raw rest reading, as `features` takes it
            resting = rest_reading(volts, codes[order], t[order], predictor.inputs.rest_s)
            rest = conductance_us(resting, front_end)
        return cls(predictor, conductance_us(volts, front_end), y, windows, front_end, rest, axes)

    def inputs(self, transform: Any) -> Any:
        """The model's inputs (torch) with the unit's map `transform` (torch, on `x`): in the
        conductance domain, the inputs the model's own kind computes from the mapped conductance of
        the reading, less those of its rest reading (as `features` does from volts)."""
        import torch

        mapped = transform(torch.from_numpy(self.x))
        if self.front_end is None:
            return mapped
        out = self._absolute(mapped)
        if self.rest is None:
            return out
        return out - self._absolute(transform(torch.from_numpy(self.rest)))

    def _absolute(self, mapped: Any) -> Any:
        import torch

        g = torch.clamp(mapped, min=MIN_CONDUCTANCE_US)
        return g if self.predictor.inputs.kind in NEEDS_CIRCUIT else volts_of_conductance(g, self.front_end)


def _losses(data: list[AngleData], forwards: list[Any], transform: Any) -> list[Any]:
    """Per angle, the mean squared error of the model reading the unit through the map, over
    `force_scale`²."""
    import torch

    out = []
    for d, forward in zip(data, forwards, strict=True):
        x = d.inputs(transform)
        if d.windows is not None:
            x = x[torch.from_numpy(d.windows)]
        force = forward(x) if d.columns is None else forward(x)[:, d.columns]
        out.append((((force - torch.from_numpy(d.y)) / force_scale(d.y)) ** 2).mean())
    return out


def _fit(
    data: list[AngleData], forwards: list[Any], p: CalibrateParams
) -> tuple[np.ndarray, np.ndarray, float, float]:
    """(matrix, offset, loss before, loss after) of one L-BFGS fit on `data`."""
    import torch

    n = data[0].x.shape[1]
    delta = torch.zeros((n, n), dtype=torch.float64, requires_grad=True)
    offset = torch.zeros(n, dtype=torch.float64, requires_grad=p.offset)
    mask = (
        torch.ones((n, n), dtype=torch.float64)
        if p.transform == "full"
        else torch.eye(n, dtype=torch.float64)
    )
    eye = torch.eye(n, dtype=torch.float64)

    def apply(x: Any) -> Any:
        return x @ (eye + delta * mask).T + offset

    def objective() -> Any:
        fit = torch.stack(_losses(data, forwards, apply)).mean()
        return fit + p.ridge * ((delta * mask) ** 2).sum() + p.ridge * (offset**2).sum()

    with torch.no_grad():
        before = float(objective())
    opt = torch.optim.LBFGS(
        [delta, offset] if p.offset else [delta], lr=1.0, max_iter=p.max_iter, line_search_fn="strong_wolfe"
    )

    def closure() -> Any:
        opt.zero_grad()
        loss = objective()
        loss.backward()
        return loss

    with exact_lbfgs():
        opt.step(closure)
    with torch.no_grad():
        after = float(objective())
    return (eye + delta * mask).detach().numpy().copy(), offset.detach().numpy().copy(), before, after


def _held_out_loss(d: AngleData, forward: Any, matrix: np.ndarray, offset: np.ndarray) -> float:
    import torch

    a, b = torch.from_numpy(matrix), torch.from_numpy(offset)
    with torch.no_grad():
        return float(_losses([d], [forward], lambda x: x @ a.T + b)[0])


@dataclass(frozen=True)
class _Fold:
    """One L-BFGS fit of `fit_transform`, a job for a worker process: on every angle of `angles`
    (`held_out` None), or on all but `held_out`, which it then scores. Predictors travel as their
    checkpoints (a network's class is built at run time and does not pickle)."""

    angles: tuple[tuple[dict[str, Any], np.ndarray, np.ndarray, np.ndarray | None, Circuit | None, Any], ...]
    p: CalibrateParams
    seed: int
    held_out: int | None


def _fold_of(data: list[AngleData], p: CalibrateParams, seed: int, held_out: int | None) -> _Fold:
    angles = tuple((d.predictor.checkpoint, d.x, d.y, d.windows, d.front_end, d.rest, d.axes) for d in data)
    return _Fold(angles, p, seed, held_out)


def _run_fold(fold: _Fold) -> tuple[np.ndarray, np.ndarray, float, float, float, float]:
    """(matrix, offset, loss before, loss after) of the fold's fit, then, for a leave-one-angle-out
    fold, the angle left out's loss through the identity and through the fitted transform."""
    data = [AngleData(Predictor(c), x, y, w, fe, rest, ax) for c, x, y, w, fe, rest, ax in fold.angles]
    forwards = [d.predictor.torch_forward() for d in data]
    i = fold.held_out
    with deterministic_torch(fold.seed):
        if i is None:
            return (*_fit(data, forwards, fold.p), math.nan, math.nan)
        rest = [x for j, x in enumerate(data) if j != i]
        m_i, b_i, before, after = _fit(rest, [f for j, f in enumerate(forwards) if j != i], fold.p)
        n = data[i].x.shape[1]
        held_before = _held_out_loss(data[i], forwards[i], np.eye(n), np.zeros(n))
        held_after = _held_out_loss(data[i], forwards[i], m_i, b_i)
    return m_i, b_i, before, after, held_before, held_after


def fit_transforms(
    data: dict[str, list[AngleData]], p: CalibrateParams, seed: int = 0, workers: int = 1
) -> dict[str, tuple[InputTransform, dict[str, Any]]]:
    """`fit_transform` for each model kind of `data` ({kind: its angles' data}), the fits of every
    kind on up to `workers` processes at once (the same results, in the same order, on any number)."""
    if any(not d for d in data.values()):
        raise ValueError("no calibration rows to fit a transform on")
    folds = {
        kind: [None, *range(len(d))] if p.validate_by_angle and len(d) >= 2 else [None]
        for kind, d in data.items()
    }
    jobs = [_fold_of(data[kind], p, seed, i) for kind, held in folds.items() for i in held]
    # the work: rows through the model (an LSTM reads a window of them per row) in every fold
    work = sum(len(x) * (1 if w is None else w.shape[1]) for fold in jobs for _, x, _, w, *_ in fold.angles)
    results = iter(ordered_map(_run_fold, jobs, workers=workers_for(work, WORTH_A_WORKER, workers)))
    return {kind: _decide(data[kind], [next(results) for _ in held]) for kind, held in folds.items()}


def fit_transform(
    data: list[AngleData], p: CalibrateParams, seed: int = 0
) -> tuple[InputTransform, dict[str, Any]]:
    """The unit's transform for one model kind, and what the fit did: loss before (identity) and
    after; with `p.validate_by_angle` and two angles or more, the same leave-one-angle-out (each angle scored
    by a transform fitted on the others). The identity is kept, and the report says why, when the fit
    does not lower the loss or does not lower it on held-out angles: a transform that only fits the
    calibration insertions' own noise would make the unit worse."""
    return fit_transforms({"": data}, p, seed)[""]


def _decide(
    data: list[AngleData], results: list[tuple[np.ndarray, np.ndarray, float, float, float, float]]
) -> tuple[InputTransform, dict[str, Any]]:
    """The transform and report of `fit_transform` from its folds' results (the fit on every angle,
    then each angle left out in turn)."""
    n = data[0].x.shape[1]
    matrix, b, before, after, _, _ = results[0]
    report: dict[str, Any] = {"loss_before": before, "loss_after": after}
    if len(results) > 1:
        held_before = held_after = 0.0
        for *_, held_i_before, held_i_after in results[1:]:  # summed in angle order, as always
            held_before += held_i_before / len(data)
            held_after += held_i_after / len(data)
        report["held_out_loss_before"], report["held_out_loss_after"] = held_before, held_after
    if not (math.isfinite(after) and after < before):
        report["identity_kept"] = f"the fit did not lower the loss ({before:.4g} -> {after:.4g})"
    elif (
        "held_out_loss_after" in report and not report["held_out_loss_after"] < report["held_out_loss_before"]
    ):
        report["identity_kept"] = (
            f"leave-one-angle-out, the transform does not lower the loss on the angle left out "
            f"({report['held_out_loss_before']:.4g} -> {report['held_out_loss_after']:.4g})"
        )
    if "identity_kept" in report:
        matrix, b = np.eye(n), np.zeros(n)
    return InputTransform.from_dict(
        {"matrix": matrix, "offset": b, "domain": data[0].domain}, data[0].front_end
    ), report
