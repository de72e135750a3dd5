"""Inference: a trained model behind one call, volts in, newtons out (cf. Made-With-ML's
`predict.TorchPredictor`). The low layer that the predict stage, the champion's re-scoring and
the peer benchmark all use; the simulator's client runs the exported ONNX graph instead.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from pipeline.modelling.checkpoint import FORMAT, ModelConfig, load_checkpoint
from pipeline.modelling.features import InputTransform, features, spec_of
from pipeline.modelling.inputs import network_inputs, times_of, trial_codes
from pipeline.modelling.networks import build_network, deterministic_torch
from pipeline.rig.frontend import Circuit
from pipeline.vocab import KINDS

PREDICT_CHUNK = 65_536  # rows per forward pass at prediction time


class Predictor:
    """A trained model behind one call: volts in, force in newtons out.

    Attributes: `kind`, `channels` (the order it reads them in), `inputs` (the `ModelInputs` it
    computes from the volts), `targets`, `rate_hz`, `angle_deg`, `window` (samples of history it
    uses, 1 for ls/fnn), `config`, `checkpoint`. A unit's calibration is an `InputTransform` passed
    to `predict`: it maps the unit's inputs before the model reads them.
    """

    def __init__(self, checkpoint: dict[str, Any]) -> None:
        if checkpoint.get("format") != FORMAT:
            raise ValueError(f"not a {FORMAT} checkpoint (format {checkpoint.get('format')!r})")
        self.checkpoint = checkpoint
        self.kind: str = checkpoint["kind"]
        if self.kind not in KINDS:
            raise ValueError(f"unknown model kind {self.kind!r} in checkpoint")
        self.config = ModelConfig.from_dict(checkpoint["config"])
        self.channels: tuple[str, ...] = tuple(checkpoint["channels"])
        self.inputs = spec_of(checkpoint.get("inputs"))
        self.targets: tuple[str, ...] = tuple(checkpoint["targets"])
        self.rate_hz: float = float(checkpoint["rate_hz"])
        self.angle_deg: float = float(checkpoint["angle_deg"])
        self.window: int = self.config.window
        pre = checkpoint["preprocessing"]
        self._x_mean, self._x_std, self._y_mean, self._y_std = (
            pre[k].double().numpy() for k in ("x_mean", "x_std", "y_mean", "y_std")
        )
        state = checkpoint["state_dict"]
        self._net: Any = None
        if self.kind == "ls":
            self._weight = state["weight"].double().numpy()
            self._bias = state["bias"].double().numpy()
        else:
            import torch

            with torch.random.fork_rng(
                devices=[]
            ):  # the throwaway initialisation must not use the caller's RNG
                self._net = build_network(self.config)
            self._net.load_state_dict(state)
            self._net.eval()

    def __repr__(self) -> str:
        return f"Predictor(kind={self.kind!r}, angle_deg={self.angle_deg:g}, channels={list(self.channels)})"

    def predict(
        self, frame: pd.DataFrame, transform: InputTransform | None = None, front_end: Circuit | None = None
    ) -> np.ndarray:
        """Forces (n, 3) in N for the frame's rows, in its row order.

        Reads the model's channels by name (extra columns are ignored). The LSTM builds its windows
        per (batch_id, trial_id) in t_s order; a frame without those columns is one trial in row order.
        `front_end` is the circuit of the unit that recorded the rows, when it declares its own (None:
        the one the model was trained through).
        """
        missing = [c for c in self.channels if c not in frame.columns]
        if missing:
            raise ValueError(
                f"the frame lacks the model's channel(s) {missing}: this {self.kind} model "
                f"(angle {self.angle_deg:g}°) reads {list(self.channels)}; "
                f"the frame has {list(frame.columns)}"
            )
        volts = frame[list(self.channels)].to_numpy(np.float64)
        return self._predict(volts, trial_codes(frame), times_of(frame), transform, front_end)

    def predict_arrays(
        self,
        volts: np.ndarray,
        trial_ids: Sequence[Any] | np.ndarray | None = None,
        t_s: np.ndarray | None = None,
        transform: InputTransform | None = None,
    ) -> np.ndarray:
        """Forces (n, 3) in N for volts (n, channels) in `self.channels` order, rows in time order
        within each trial; `trial_ids` (n,) labels trials, None = all rows are one trial; `t_s` the
        sample times (default: row number / rate_hz; rest-relative inputs need seconds).

        A live client can keep the last `window` samples and take the last row of the result.
        """
        volts = np.asarray(volts, dtype=np.float64)
        if volts.ndim != 2 or volts.shape[1] != len(self.channels):
            raise ValueError(
                f"volts must be (n, {len(self.channels)}) for {list(self.channels)}, got {volts.shape}"
            )
        if trial_ids is None:
            codes = np.zeros(len(volts), dtype=np.int64)
        else:
            if len(trial_ids) != len(volts):
                raise ValueError(f"{len(trial_ids)} trial ids for {len(volts)} rows")
            codes = pd.factorize(
                pd.Series(list(trial_ids) if not isinstance(trial_ids, np.ndarray) else trial_ids)
            )[0]
        if t_s is None:
            step = 1.0 / self.rate_hz if np.isfinite(self.rate_hz) and self.rate_hz > 0 else 1.0
            t_s = np.arange(len(volts), dtype=float) * step
        return self._predict(volts, codes.astype(np.int64), np.asarray(t_s, dtype=np.float64), transform)

    def _predict(
        self,
        volts: np.ndarray,
        codes: np.ndarray,
        t: np.ndarray,
        transform: InputTransform | None,
        front_end: Circuit | None = None,
    ) -> np.ndarray:
        if not np.isfinite(volts).all():
            bad = [c for c, ok in zip(self.channels, np.isfinite(volts).all(axis=0), strict=True) if not ok]
            raise ValueError(f"non-finite volts in channel(s) {bad}")
        x_in = features(volts, codes, t, self.inputs.through(front_end), transform)
        return self._forward(x_in, codes, t)

    def predict_inputs(self, x: np.ndarray, trial_ids: np.ndarray | None = None) -> np.ndarray:
        """Forces (n, 3) for model inputs `x` (n, channels) already computed from volts (what the
        deployable graph reads), rows in time order within each trial."""
        x = np.asarray(x, dtype=np.float64)
        codes = np.zeros(len(x), np.int64) if trial_ids is None else pd.factorize(np.asarray(trial_ids))[0]
        return self._forward(x, codes.astype(np.int64), np.arange(len(x), dtype=float))

    def _forward(self, x_in: np.ndarray, codes: np.ndarray, t: np.ndarray) -> np.ndarray:
        if len(x_in) == 0:
            return np.zeros((0, len(self.targets)))
        if self.kind == "ls":
            return x_in @ self._weight.T + self._bias
        import torch

        x = torch.from_numpy(network_inputs(self.config, (x_in - self._x_mean) / self._x_std, codes, t))
        with deterministic_torch(), torch.no_grad():  # same thread count as training: same float sums
            # fixed-size chunks bound the memory of long recordings (an LSTM keeps every step's state)
            y = torch.cat([self._net(x[i : i + PREDICT_CHUNK]) for i in range(0, len(x), PREDICT_CHUNK)])
        return y.double().numpy() * self._y_std + self._y_mean

    def torch_forward(self) -> Any:
        """The frozen model as a float64 torch function of its inputs, (n, c) -> (n, 3) N, that
        gradients flow through (LSTM: (n, window, c) windows); for fitting a unit's calibration."""
        import copy

        import torch

        y_mean, y_std = torch.from_numpy(self._y_mean), torch.from_numpy(self._y_std)
        if self.kind == "ls":
            weight, bias = torch.from_numpy(self._weight), torch.from_numpy(self._bias)
            return lambda x: x @ weight.T + bias
        net = copy.deepcopy(self._net).double()
        for p in net.parameters():
            p.requires_grad_(False)
        x_mean, x_std = torch.from_numpy(self._x_mean), torch.from_numpy(self._x_std)
        return lambda x: net((x - x_mean) / x_std) * y_std + y_mean


def load_predictor(model_dir_or_file: Path) -> Predictor:
    """The predictor of a trained model: `load_predictor(Path("models/fnn/30")).predict(df)`."""
    return Predictor(load_checkpoint(model_dir_or_file))
