"""The front of a deployed graph: the estimator's raw volts, their rest reading and the unit's
calibration in, the model's inputs out, in torch so that it exports to ONNX with the network behind
it (`pipeline.modelling.export`).

It computes what `needlecue_runtime.features.features` computes, in float64 and with the same
formulas (`needlecue_runtime.frontend`), so that a simulator in any language feeds the graph nothing but
what the estimator sends: its readings (counts or volts, `volts_per_count` scales them). The unit's
calibration is data, not code: the three `unit_*` inputs that `features.unit_inputs` encodes
(identity and no circuit: the model's own reading, uncalibrated).

torch is imported inside the functions, so importing this module is cheap.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from needlecue_runtime.features import (
    GROUND_DIVIDER,
    MIN_CONDUCTANCE_US,
    ON_CONDUCTANCE,
    SUPPLY_DIVIDER,
    TRANSIMPEDANCE,
    ModelInputs,
    encode_circuit,
)
from needlecue_runtime.frontend import MAX_KOHM, MIN_KOHM

if TYPE_CHECKING:
    import torch


def _resistance(v: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    """`frontend.resistance_of` for an encoded circuit `c` (`features.encode_circuit`), any of them."""
    import torch

    code, a, b, series, offset = c[0], c[1], c[2], c[3], c[4]
    eps = 1e-6 * a
    ratio = a / torch.minimum(torch.maximum(v, eps), a - eps) - 1.0
    divider = torch.where(code == SUPPLY_DIVIDER, b * ratio, b / ratio)
    transimpedance = a * b / torch.maximum(v - offset, 1e-9 * a)
    r = torch.where(code == TRANSIMPEDANCE, transimpedance, divider)
    low, high = torch.tensor(MIN_KOHM, dtype=v.dtype), torch.tensor(MAX_KOHM, dtype=v.dtype)
    return torch.minimum(torch.maximum(r - series, low), high)


def _volts_of_conductance(g: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    """`frontend.volts_of_conductance` for an encoded circuit."""
    import torch

    code, a, b, series, offset = c[0], c[1], c[2], c[3], c[4]
    r = 1e3 / g + series
    supply, ground = a / (1.0 + r / b), a / (1.0 + b / r)
    transimpedance = offset + a * b / r
    return torch.where(
        code == SUPPLY_DIVIDER, supply, torch.where(code == GROUND_DIVIDER, ground, transimpedance)
    )


def _affine(x: torch.Tensor, matrix: torch.Tensor, offset: torch.Tensor) -> torch.Tensor:
    """x A^T + b over the last axis, as products and a sum: a float64 MatMul next to a transpose is
    fused by some onnxruntime versions into an operator that has no float64 kernel."""
    return (x.unsqueeze(-2) * matrix).sum(-1) + offset


def front_module(spec: ModelInputs, sequence: bool) -> torch.nn.Module:
    """(reading, rest_reading, volts_per_count, unit_matrix, unit_offset, unit_circuit) -> the model's
    inputs, float64: (batch, window, channels) windows for a `sequence` model (the LSTM), else
    (batch, channels) of the last sample."""
    import torch
    from torch import nn

    own = encode_circuit(spec.front_end) if spec.needs_circuit else np.zeros(6)

    class Front(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.register_buffer("own", torch.from_numpy(own))  # the model's circuit (its training units')

        def _absolute(self, v: Any, matrix: Any, offset: Any, unit: Any) -> Any:
            mapped = torch.maximum(
                _affine(1e3 / _resistance(v, unit), matrix, offset),
                torch.tensor(MIN_CONDUCTANCE_US, dtype=v.dtype),
            )
            calibrated = unit[ON_CONDUCTANCE] > 0.5
            v = torch.where(calibrated, _volts_of_conductance(mapped, unit), v)  # the calibrated volts
            if not spec.needs_circuit:
                return v
            # read through the unit's circuit if it declares one, else through the model's own
            return torch.where(unit[0] > 0.5, 1e3 / _resistance(v, unit), 1e3 / _resistance(v, self.own))

        def forward(self, reading: Any, rest: Any, scale: Any, matrix: Any, offset: Any, unit: Any) -> Any:
            x = self._absolute(reading * scale, matrix, offset, unit)  # counts to volts (1: volts already)
            if spec.kind.startswith("rest_"):
                x = x - self._absolute(rest * scale, matrix, offset, unit)
            x = torch.where(unit[ON_CONDUCTANCE] > 0.5, x, _affine(x, matrix, offset))  # on the inputs
            return x if sequence else x[:, -1, :]

    return Front().eval()
