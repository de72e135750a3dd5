"""What a model kind is: the one protocol every kind's module implements (docs/model-kinds.md).

A kind says how its config follows from its params section, how it trains, how the inputs choice
stands in for it, and how a trained model of it runs (`Runtime`: numpy for the predict stage, torch
for a unit's calibration, a torch module for the ONNX graph). Everything else (the train stage,
`Predictor`, the export, the calibration) asks the kind and never branches on its name.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar, NamedTuple, Protocol

import numpy as np
import pandas as pd

from needlecue_runtime.features import ModelInputs
from pipeline.config import InputParams, Section
from pipeline.logs import Log
from pipeline.modelling.checkpoint import ModelConfig

if TYPE_CHECKING:
    import torch


@dataclass(frozen=True)
class StandIn:
    """How the inputs choice (`pipeline.modelling.choice`) stands in for a model kind without training
    it; each kind gives its own (`ModelKind.stand_in`)."""

    linear: bool  # least squares on the inputs as they are: the model is linear in them
    intercept: bool = True
    lags: tuple[int, ...] = ()  # samples back in the trial: the stand-in of a model's memory

    def describe(self) -> str:
        if self.linear:
            return "least squares on the inputs" + ("" if self.intercept else ", no intercept")
        lags = f", lags {list(self.lags)} samples" if self.lags else ""
        return "ridge on inputs, squares and pairwise products" + lags


class KindParams(Protocol):
    """What training reads of any kind's params section (a frozen `config.Section` defined in the
    kind's module, `ModelKind.params`): `inputs`, what the model reads. The rest is the kind's own."""

    @property
    def inputs(self) -> InputParams: ...

    def model_dump(self, *, mode: str = "python") -> dict[str, Any]: ...


class Fitted(NamedTuple):
    """What a kind's training gives: the checkpoint's tensors and what the fit did."""

    state: dict[str, Any]  # the checkpoint's state_dict (tensors)
    preprocessing: dict[str, Any]  # x_mean, x_std, y_mean, y_std (float64 tensors; identity: unscaled)
    history: list[dict[str, float]]  # per epoch: epoch, train_loss, val_loss
    summary: dict[str, Any]  # epochs_run, best_epoch, best_val_loss, early_stopping


class Runtime(Protocol):
    """A trained model of a kind, loaded from its checkpoint's config, state and preprocessing."""

    def forward(self, x: np.ndarray, codes: np.ndarray, t: np.ndarray) -> np.ndarray:
        """Forces (n, 3) in N from model inputs `x` (n, channels), float64; `codes` and `t` order
        the rows into trials for a kind with memory."""
        ...

    def torch_forward(self) -> Callable[[torch.Tensor], torch.Tensor]:
        """The frozen model as a float64 torch function of its inputs, (n, c) -> (n, 3) N, that
        gradients flow through ((n, window, c) windows for a sequence kind)."""
        ...

    def graph(self) -> torch.nn.Module:
        """The model as a float32 torch module, inputs in, newtons out, for the ONNX graph."""
        ...


class ModelKind(ABC):
    """One kind of force model. A subclass sets `name` (the params section and `vocab.KINDS` entry),
    `params` (its `config.Section`, defined in its module) and, if it reads a window of samples per
    row, `sequence`; the report names it by `label` and draws it in `color`."""

    name: ClassVar[str]
    params: ClassVar[type[Section]]
    sequence: ClassVar[bool] = False  # reads the last `window` samples of the trial per row
    color: ClassVar[str | None] = None  # its colour in the report's figures (None: matplotlib's next)

    @property
    def label(self) -> str:
        """How the report names the kind: its name in capitals, unless the kind says otherwise."""
        return self.name.upper()

    @abstractmethod
    def config(self, params: Any, n_in: int) -> ModelConfig:
        """The checkpoint's config of a model of this kind trained with `params` on `n_in` inputs."""

    @abstractmethod
    def stand_in(self, params: Any) -> StandIn:
        """How the inputs choice stands in for this kind (pipeline.modelling.choice)."""

    @abstractmethod
    def train(
        self,
        cfg: ModelConfig,
        params: Any,
        spec: ModelInputs,
        train: pd.DataFrame,
        val: pd.DataFrame,
        channels: list[str],
        log: Log,
    ) -> Fitted:
        """Fit on `train`, validated (early-stopped, if the kind does) on `val`, which may be empty."""

    @abstractmethod
    def load(self, cfg: ModelConfig, state: dict[str, Any], preprocessing: dict[str, Any]) -> Runtime:
        """A trained model of this kind from its checkpoint's parts."""

    def import_backends(self) -> None:
        """Import what training needs, so that the training clock measures the work, not imports."""
        import torch  # noqa: F401

    def window(self, cfg: ModelConfig) -> int:
        """Samples per prediction row: the config's window for a sequence kind, else 1."""
        return cfg.window if self.sequence else 1


def preprocessing(x_mean: np.ndarray, x_std: np.ndarray, y_mean: np.ndarray, y_std: np.ndarray) -> dict:
    """The checkpoint's standardisation of inputs and targets, as float64 tensors."""
    import torch

    arrays = {"x_mean": x_mean, "x_std": x_std, "y_mean": y_mean, "y_std": y_std}
    return {k: torch.tensor(np.asarray(v, dtype=np.float64)) for k, v in arrays.items()}
