"""A trained linear model, F = W x + b on the unscaled inputs: the runtime of `ls` (and of any kind
whose weights are one matrix and one offset)."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from pipeline.modelling.kinds.graph import standardised

if TYPE_CHECKING:
    import torch


class LinearModel:
    """`weight` (3, c) and `bias` (3,), the checkpoint's state; float64 arithmetic."""

    def __init__(self, weight: torch.Tensor, bias: torch.Tensor) -> None:
        self.state = {"weight": weight, "bias": bias}
        self.weight, self.bias = weight.double().numpy(), bias.double().numpy()

    def forward(self, x: np.ndarray, codes: np.ndarray, t: np.ndarray) -> np.ndarray:
        return x @ self.weight.T + self.bias

    def torch_forward(self) -> Callable[[torch.Tensor], torch.Tensor]:
        import torch

        weight, bias = torch.from_numpy(self.weight), torch.from_numpy(self.bias)
        return lambda x: x @ weight.T + bias

    def graph(self) -> torch.nn.Module:
        import torch
        from torch import nn

        n_out, n_in = self.weight.shape
        with torch.random.fork_rng(devices=[]):  # the throwaway initialisation must not use the caller's RNG
            net = nn.Linear(n_in, n_out)
        net.load_state_dict({k: v.float() for k, v in self.state.items()})
        return standardised(net, None)
