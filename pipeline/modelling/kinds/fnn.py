"""`fnn`: the paper's feed-forward network, channels -> 20 -> 20 -> 3 (Sec. III-B), on the inputs of
the current sample."""

from __future__ import annotations

from collections import OrderedDict
from typing import TYPE_CHECKING, Annotated, Literal

from pydantic import Field

from pipeline.config import InputParams, Section
from pipeline.modelling.checkpoint import ModelConfig
from pipeline.modelling.kinds.base import StandIn
from pipeline.modelling.kinds.network import NetworkKind

if TYPE_CHECKING:
    import torch


class FNNParams(Section):
    """`fnn`: the paper's feed-forward network on the current voltages."""

    hidden: tuple[Annotated[int, Field(ge=1)], ...] = (20, 20)
    activation: Literal["tanh", "relu"] = "tanh"
    lr: float = Field(0.003, gt=0)
    weight_decay: float = Field(0.0, ge=0)
    batch_size: int = Field(256, ge=1)
    max_epochs: int = Field(300, ge=1)
    patience: int = Field(25, ge=1, description="epochs without a better validation loss before stopping")
    ema: float = Field(0.0, ge=0, lt=1, description="running weight average per step, validated and saved")
    seed: int = 0
    inputs: InputParams = InputParams()


class FNN(NetworkKind):
    name = "fnn"
    params = FNNParams
    color = "tab:blue"

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
