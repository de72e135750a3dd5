"""What the network kinds share: training by Adam with early stopping on standardised data, and the
trained network's runtime. A network kind (`fnn`, `lstm`) adds its module and its config.

Training is bit-for-bit deterministic: seeded initialisation and shuffling, deterministic
algorithms, one intra-op thread (`determinism.TRAIN_THREADS`). torch is imported inside the
functions that need it.
"""

from __future__ import annotations

import copy
import math
from abc import abstractmethod
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd

from needlecue_runtime.features import ModelInputs
from needlecue_runtime.vocab import axes_of
from pipeline.logs import Log
from pipeline.modelling.checkpoint import ModelConfig
from pipeline.modelling.determinism import deterministic_torch
from pipeline.modelling.inputs import (
    column_stats,
    features_of,
    sequence_order,
    times_of,
    trial_codes,
    window_index,
)
from pipeline.modelling.kinds.adam import Adam, flatten
from pipeline.modelling.kinds.base import Fitted, ModelKind, preprocessing
from pipeline.modelling.kinds.graph import standardised

if TYPE_CHECKING:
    import torch

PREDICT_CHUNK = 65_536  # rows per forward pass at prediction time


class NetworkKind(ModelKind):
    """A torch network trained on standardised inputs and targets; its params section has `lr`,
    `weight_decay`, `batch_size`, `max_epochs`, `patience`, `ema` and `seed`."""

    @abstractmethod
    def module(self, cfg: ModelConfig) -> torch.nn.Module:
        """The torch module of `cfg` (float32, freshly initialised from the global RNG)."""

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
        """Adam on standardised data, seeded shuffling, early stopping on val MSE keeping the best weights."""
        import torch

        window = self.sequence_window(cfg)
        x_mean, x_std = column_stats(features_of(train, channels, spec))
        targets = list(axes_of(train.columns))
        y = train[targets].to_numpy(np.float64)
        y_mean, y_std = column_stats(y)
        x_tr = torch.from_numpy(inputs_of(train, channels, x_mean, x_std, spec, window))
        y_tr = torch.from_numpy(((y - y_mean) / y_std).astype(np.float32))
        has_val = not val.empty
        if has_val:
            x_va = torch.from_numpy(inputs_of(val, channels, x_mean, x_std, spec, window))
            y_val = val[targets].to_numpy(np.float64)
            y_va = torch.from_numpy(((y_val - y_mean) / y_std).astype(np.float32))
        else:
            log(f"no validation rows: no early stopping, training all {params.max_epochs} epochs")

        n, bs = len(x_tr), params.batch_size
        every = max(1, params.max_epochs // 10)
        history: list[dict[str, float]] = []
        with deterministic_torch(params.seed):
            net = self.module(cfg)  # initialised from the seeded (forked) global RNG
            gen = torch.Generator().manual_seed(params.seed)
            opt = Adam(net.parameters(), lr=params.lr, weight_decay=params.weight_decay)
            loss_fn = torch.nn.MSELoss()
            # The averaged copy is what gets validated and saved: it smooths the step-to-step noise of
            # the SGD iterate, so the early-stopping choice depends less on where one epoch happened to end.
            avg = self.module(cfg) if params.ema > 0 else net
            if params.ema > 0:
                avg.load_state_dict(net.state_dict())
                avg_flat = flatten(list(avg.parameters()))  # in the order of opt.flat (same config)
            best_state = {k: v.detach().clone() for k, v in avg.state_dict().items()}
            best_val, best_epoch, epoch = math.inf, 0, 0
            for epoch in range(1, params.max_epochs + 1):
                net.train()
                perm = torch.randperm(n, generator=gen)
                total = torch.zeros(())
                for i in range(0, n, bs):
                    idx = perm[i : i + bs]
                    opt.zero_grad()
                    loss = loss_fn(net(x_tr[idx]), y_tr[idx])
                    loss.backward()
                    opt.step()
                    if params.ema > 0:
                        with torch.no_grad():
                            avg_flat.lerp_(opt.flat, 1 - params.ema)
                    total += loss.detach() * len(idx)
                train_loss = float(total) / n
                val_loss = math.nan
                if has_val:
                    avg.eval()
                    with torch.no_grad():
                        val_loss = float(loss_fn(avg(x_va), y_va))
                history.append({"epoch": epoch, "train_loss": train_loss, "val_loss": val_loss})
                if not has_val or val_loss < best_val:
                    best_val, best_epoch = val_loss, epoch
                    best_state = {k: v.detach().clone() for k, v in avg.state_dict().items()}
                if epoch % every == 0:
                    log(f"epoch {epoch:4d}  train loss {train_loss:.5f}  val loss {val_loss:.5f}")
                if has_val and epoch - best_epoch >= params.patience:
                    break

        summary = {
            "epochs_run": epoch,
            "best_epoch": best_epoch,
            "best_val_loss": best_val if has_val else None,
            "early_stopping": has_val,
        }
        return Fitted(best_state, preprocessing(x_mean, x_std, y_mean, y_std), history, summary)

    def load(self, cfg: ModelConfig, state: dict[str, Any], preprocessing: dict[str, Any]) -> NetworkModel:
        return NetworkModel(self, cfg, state, preprocessing)

    def sequence_window(self, cfg: ModelConfig) -> int | None:
        """The window the network reads per row, or None for a network of the current sample."""
        return cfg.window if self.sequence else None


def network_inputs(x_std: np.ndarray, codes: np.ndarray, t: np.ndarray, window: int | None) -> np.ndarray:
    """(n, c) without a window; (n, window, c) with one, each row's window built within its trial."""
    if window is None:
        return x_std.astype(np.float32)
    order, start = sequence_order(codes, t)
    windows = x_std[order][window_index(start, window)]  # sorted rows' windows
    out = np.empty_like(windows)
    out[order] = windows  # back to the frame's row order
    return out.astype(np.float32)


def inputs_of(
    frame: pd.DataFrame,
    channels: list[str],
    x_mean: np.ndarray,
    x_std: np.ndarray,
    spec: ModelInputs,
    window: int | None,
) -> np.ndarray:
    """Standardised float32 network inputs of a frame's rows, in the frame's order."""
    x = (features_of(frame, channels, spec) - x_mean) / x_std
    return network_inputs(x, trial_codes(frame), times_of(frame), window)


class NetworkModel:
    """A trained network with its checkpoint's standardisation."""

    def __init__(
        self, kind: NetworkKind, cfg: ModelConfig, state: dict[str, Any], pre: dict[str, Any]
    ) -> None:
        import torch

        self.pre = pre
        self.window = kind.sequence_window(cfg)
        self.x_mean, self.x_std, self.y_mean, self.y_std = (
            pre[k].double().numpy() for k in ("x_mean", "x_std", "y_mean", "y_std")
        )
        with torch.random.fork_rng(devices=[]):  # the throwaway initialisation must not use the caller's RNG
            self.net = kind.module(cfg)
        self.net.load_state_dict(state)
        self.net.eval()

    def forward(self, x: np.ndarray, codes: np.ndarray, t: np.ndarray) -> np.ndarray:
        import torch

        z = torch.from_numpy(network_inputs((x - self.x_mean) / self.x_std, codes, t, self.window))
        with deterministic_torch(), torch.no_grad():  # same thread count as training: same float sums
            # fixed-size chunks bound the memory of long recordings (an LSTM keeps every step's state)
            y = torch.cat([self.net(z[i : i + PREDICT_CHUNK]) for i in range(0, len(z), PREDICT_CHUNK)])
        return y.double().numpy() * self.y_std + self.y_mean

    def torch_forward(self) -> Callable[[torch.Tensor], torch.Tensor]:
        import torch

        y_mean, y_std = torch.from_numpy(self.y_mean), torch.from_numpy(self.y_std)
        net = copy.deepcopy(self.net).double()
        for p in net.parameters():
            p.requires_grad_(False)
        x_mean, x_std = torch.from_numpy(self.x_mean), torch.from_numpy(self.x_std)
        return lambda x: net((x - x_mean) / x_std) * y_std + y_mean

    def graph(self) -> torch.nn.Module:
        return standardised(copy.deepcopy(self.net), self.pre)  # a copy: standardised casts it in place
