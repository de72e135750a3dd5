"""`ls`: the paper's calibration matrix, eq. (1)-(2): F = C x fitted by least squares, with no
intercept by default (scipy's `lstsq`, as scikit-learn's `LinearRegression(fit_intercept=False)`
does), on the unscaled inputs."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pandas as pd

from needlecue_runtime.features import ModelInputs
from needlecue_runtime.vocab import axes_of
from pipeline.config import InputParams, Section
from pipeline.logs import Log
from pipeline.modelling.checkpoint import ModelConfig
from pipeline.modelling.inputs import column_stats, features_of
from pipeline.modelling.kinds.base import Fitted, ModelKind, StandIn, preprocessing
from pipeline.modelling.kinds.linear import LinearModel

LSTSQ_CUTOFF = 1e-6  # relative singular-value cutoff: scikit-learn's LinearRegression `tol` default


class LSParams(Section):
    """`ls`: the calibration matrix of eq. (1)-(2)."""

    fit_intercept: bool = False  # the paper's F = C v has none; zero volts -> zero force
    inputs: InputParams = InputParams()


class LS(ModelKind):
    name = "ls"
    params = LSParams
    color = "tab:red"

    def config(self, params: LSParams, n_in: int) -> ModelConfig:
        return ModelConfig(kind=self.name, n_in=n_in)

    def stand_in(self, params: LSParams) -> StandIn:
        return StandIn(linear=True, intercept=params.fit_intercept)  # the model itself

    def import_backends(self) -> None:
        super().import_backends()
        import scipy.linalg  # noqa: F401

    def train(
        self,
        cfg: ModelConfig,
        params: LSParams,
        spec: ModelInputs,
        train: pd.DataFrame,
        val: pd.DataFrame,
        channels: list[str],
        log: Log,
    ) -> Fitted:
        """Eq. (2) on the unscaled inputs: that is the paper's method, and scaling would add an offset."""
        import torch

        x = features_of(train, channels, spec)
        targets = list(axes_of(train.columns))
        y = train[targets].to_numpy(np.float64)
        _, y_std = column_stats(y)  # only to report a loss on the same scale as the networks'
        weight, bias = least_squares(x, y, params.fit_intercept)
        train_loss = _scaled_mse(x @ weight.T + bias, y, y_std)
        if val.empty:
            val_loss = math.nan
        else:
            xv = features_of(val, channels, spec)
            val_loss = _scaled_mse(xv @ weight.T + bias, val[targets].to_numpy(np.float64), y_std)
        state = {"weight": torch.from_numpy(weight), "bias": torch.from_numpy(bias)}
        n = len(channels)
        pre = preprocessing(np.zeros(n), np.ones(n), np.zeros(len(targets)), np.ones(len(targets)))
        history = [{"epoch": 1, "train_loss": train_loss, "val_loss": val_loss}]
        summary = {
            "epochs_run": 1,
            "best_epoch": 1,
            "best_val_loss": None if math.isnan(val_loss) else val_loss,
            "early_stopping": False,
        }
        return Fitted(state, pre, history, summary)

    def load(self, cfg: ModelConfig, state: dict[str, Any], preprocessing: dict[str, Any]) -> LinearModel:
        return LinearModel(state["weight"], state["bias"])


def least_squares(x: np.ndarray, y: np.ndarray, intercept: bool) -> tuple[np.ndarray, np.ndarray]:
    """(weight, bias) of y ~ x @ weight.T + bias: scikit-learn's `LinearRegression(fit_intercept=
    intercept)`, step for step (centre with an intercept, then LAPACK's gelsd with its default
    cutoff), so the same bytes; without importing scikit-learn, which took ~1.5 s of each ls stage."""
    from scipy import linalg

    x_offset = x.mean(axis=0) if intercept else np.zeros(x.shape[1])
    y_offset = y.mean(axis=0) if intercept else np.zeros(y.shape[1])
    coef, *_ = linalg.lstsq(x - x_offset, y - y_offset, cond=LSTSQ_CUTOFF)
    weight = np.array(coef.T, dtype=np.float64)  # a copy: not a view into lstsq's work array
    return weight, y_offset - x_offset @ weight.T


def _scaled_mse(pred: np.ndarray, y: np.ndarray, y_std: np.ndarray) -> float:
    return float(np.mean(((pred - y) / y_std) ** 2)) if len(y) else math.nan
