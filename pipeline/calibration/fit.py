"""Fitting one unit's input transform through frozen models: x' = x A^T + b such that each shared
model, reading x', gives the reference force of the unit's calibration trials at its angle.

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

from pipeline.config import CalibrateParams
from pipeline.modelling.features import InputTransform
from pipeline.modelling.inputs import features_of, sequence_order, times_of, trial_codes, window_index
from pipeline.modelling.networks import deterministic_torch, exact_lbfgs
from pipeline.modelling.predict import Predictor
from pipeline.rig.frontend import Circuit
from pipeline.vocab import AXES

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
    """One angle's calibration rows as a frozen model reads them, in trial-time order."""

    predictor: Predictor
    x: np.ndarray  # (n, c) the model's inputs, before the unit's transform
    y: np.ndarray  # (n, 3) reference force, N
    windows: np.ndarray | None  # (n, window) row positions of each row's LSTM window, or None

    @classmethod
    def of(cls, predictor: Predictor, frame: pd.DataFrame, front_end: Circuit | None = None) -> AngleData:
        """The rows as the model reads them, through the unit's own circuit if it declares one."""
        codes, t = trial_codes(frame), times_of(frame)
        order, start = sequence_order(codes, t)
        x = features_of(frame, list(predictor.channels), predictor.inputs.through(front_end))[order]
        y = frame[list(AXES)].to_numpy(np.float64)[order]
        windows = window_index(start, predictor.window) if predictor.kind == "lstm" else None
        return cls(predictor, x, y, windows)


def _losses(data: list[AngleData], forwards: list[Any], transform: Any) -> list[Any]:
    """Per angle, the mean squared error of the model on the transformed inputs over `force_scale`²."""
    import torch

    out = []
    for d, forward in zip(data, forwards, strict=True):
        x = transform(torch.from_numpy(d.x))
        if d.windows is not None:
            x = x[torch.from_numpy(d.windows)]
        out.append((((forward(x) - torch.from_numpy(d.y)) / force_scale(d.y)) ** 2).mean())
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


def fit_transform(
    data: list[AngleData], p: CalibrateParams, seed: int = 0
) -> tuple[InputTransform, dict[str, Any]]:
    """The unit's transform for one model kind, and what the fit did: loss before (identity) and
    after; with `p.validate_by_angle` and two angles or more, the same leave-one-angle-out (each angle scored
    by a transform fitted on the others). The identity is kept, and the report says why, when the fit
    does not lower the loss or does not lower it on held-out angles: a transform that only fits the
    calibration insertions' own noise would make the unit worse."""
    if not data:
        raise ValueError("no calibration rows to fit a transform on")
    n = data[0].x.shape[1]
    forwards = [d.predictor.torch_forward() for d in data]
    with deterministic_torch(seed):
        matrix, b, before, after = _fit(data, forwards, p)
        report: dict[str, Any] = {"loss_before": before, "loss_after": after}
        if p.validate_by_angle and len(data) >= 2:
            identity = np.eye(n), np.zeros(n)
            held_before = held_after = 0.0
            for i, d in enumerate(data):
                rest = [x for j, x in enumerate(data) if j != i]
                m_i, b_i, _, _ = _fit(rest, [f for j, f in enumerate(forwards) if j != i], p)
                held_before += _held_out_loss(d, forwards[i], *identity) / len(data)
                held_after += _held_out_loss(d, forwards[i], m_i, b_i) / len(data)
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
        return InputTransform.identity(n), report
    return InputTransform.from_dict({"matrix": matrix, "offset": b}), report
