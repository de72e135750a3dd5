"""`lstm`: an LSTM on the last `window` input samples of the same trial (Sec. VI), the first samples
of a trial padded by repeating its first sample, predicting the force at the last one."""

from __future__ import annotations

import functools
from typing import TYPE_CHECKING

from pydantic import Field

from pipeline.config import InputParams, Section
from pipeline.modelling.checkpoint import ModelConfig
from pipeline.modelling.kinds.base import StandIn
from pipeline.modelling.kinds.network import NetworkKind

if TYPE_CHECKING:
    import torch


class LSTMParams(Section):
    """`lstm`: an LSTM on a window of the estimator's own recent voltages."""

    window: int = Field(15, ge=1, description="samples, including the current one")
    hidden: int = Field(24, ge=1)
    layers: int = Field(1, ge=1)
    lr: float = Field(0.005, gt=0)
    weight_decay: float = Field(0.0, ge=0)
    batch_size: int = Field(128, ge=1)
    max_epochs: int = Field(60, ge=1)
    patience: int = Field(10, ge=1, description="epochs without a better validation loss before stopping")
    ema: float = Field(0.0, ge=0, lt=1, description="running weight average per step, validated and saved")
    seed: int = 0
    inputs: InputParams = InputParams()


class LSTM(NetworkKind):
    name = "lstm"
    params = LSTMParams
    color = "tab:green"
    sequence = True

    def config(self, params: LSTMParams, n_in: int) -> ModelConfig:
        hidden = (params.hidden,) * params.layers
        return ModelConfig(self.name, n_in, hidden=hidden, activation="tanh", window=params.window)

    def stand_in(self, params: LSTMParams) -> StandIn:
        """The networks' ridge, plus the inputs a quarter and a half of the window back (its memory)."""
        w = params.window
        lags = tuple(sorted({max(1, w // 4), max(1, w // 2)})) if w > 1 else ()
        return StandIn(linear=False, lags=lags)

    def module(self, cfg: ModelConfig) -> torch.nn.Module:
        if len(set(cfg.hidden)) != 1:
            raise ValueError(f"an LSTM's layers share one width, got hidden={cfg.hidden}")
        return _lstm_class()(cfg)


@functools.cache
def _lstm_class() -> type:
    """The LSTM regressor's module class (defined lazily so that importing this file skips torch)."""
    from torch import nn

    class LSTMRegressor(nn.Module):
        """Stacked LSTM over the window; a linear head on the last step's output."""

        def __init__(self, cfg: ModelConfig) -> None:
            super().__init__()
            self.lstm = nn.LSTM(cfg.n_in, cfg.hidden[0], num_layers=len(cfg.hidden), batch_first=True)
            self.head = nn.Linear(cfg.hidden[0], cfg.n_out)

        def forward(self, x: torch.Tensor) -> torch.Tensor:
            out, _ = self.lstm(x)
            return self.head(out[:, -1])

    return LSTMRegressor
