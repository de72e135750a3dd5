"""`fnn`: the paper's feed-forward network, channels -> 20 -> 20 -> 3 (Sec. III-B), on the inputs of
the current sample."""

from __future__ import annotations

from collections import OrderedDict
from typing import TYPE_CHECKING

from pipeline.config import FNNParams
from pipeline.modelling.checkpoint import ModelConfig
from pipeline.modelling.kinds.base import StandIn
from pipeline.modelling.kinds.network import NetworkKind

if TYPE_CHECKING:
    import torch


class FNN(NetworkKind):
    name = "fnn"
    params = FNNParams

    def config(self, params: FNNParams, n_in: int) -> ModelConfig:
        return ModelConfig(self.name, n_in, hidden=tuple(params.hidden), activation=params.activation)

    def stand_in(self, params: FNNParams) -> StandIn:
        return StandIn(linear=False)  # ridge on the inputs, their squares and pairwise products

    def module(self, cfg: ModelConfig) -> torch.nn.Module:
        from torch import nn

        act = {"tanh": nn.Tanh, "relu": nn.ReLU}[cfg.activation]
        layers: OrderedDict[str, nn.Module] = OrderedDict()
        width = cfg.n_in
        for i, h in enumerate(cfg.hidden, start=1):
            layers[f"fc{i}"] = nn.Linear(width, h)
            layers[f"act{i}"] = act()
            width = h
        layers["out"] = nn.Linear(width, cfg.n_out)
        return nn.Sequential(layers)
