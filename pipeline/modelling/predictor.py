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

from needlecue_runtime.features import InputTransform, features, spec_of
from needlecue_runtime.frontend import Circuit
from pipeline.modelling.checkpoint import checkpoint_meta, load_checkpoint
from pipeline.modelling.inputs import times_of, trial_codes
from pipeline.modelling.kinds import kind_of


class Predictor:
    """A trained model behind one call: volts in, force in newtons out.

    Attributes: `kind` (its name), `model_kind` (`pipeline.modelling.kinds`), `channels` (the order
    it reads them in), `inputs` (the `ModelInputs` it computes from the volts), `targets`, `rate_hz`,
    `angle_deg`, `window` (samples of history it uses, 1 for ls/fnn), `sequence` (it reads them as
    a window per row), `config`, `checkpoint`. A unit's calibration is an `InputTransform` passed
    to `predict`: it maps the unit's inputs before the model reads them.
    """

    def __init__(self, checkpoint: dict[str, Any]) -> None:
        meta = checkpoint_meta(checkpoint)
        self.checkpoint = checkpoint
        self.kind: str = meta.kind
        self.model_kind = kind_of(self.kind, "run")
        self.config = meta.config
        self.channels: tuple[str, ...] = tuple(meta.channels)
        self.inputs = spec_of(meta.inputs)
        self.targets: tuple[str, ...] = tuple(meta.targets)
        self.rate_hz: float = meta.rate_hz
        self.angle_deg: float = meta.angle_deg
        self.window: int = self.model_kind.window(self.config)
        self.sequence: bool = self.model_kind.sequence  # reads a window of samples per row
        self._model = self.model_kind.load(self.config, checkpoint["state_dict"], checkpoint["preprocessing"])

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
        return self._model.forward(x_in, codes, t)

    def torch_forward(self) -> Any:
        """The frozen model as a float64 torch function of its inputs, (n, c) -> (n, 3) N, that
        gradients flow through (a sequence kind: (n, window, c) windows); for fitting a unit's
        calibration."""
        return self._model.torch_forward()


def load_predictor(model_dir_or_file: Path) -> Predictor:
    """The predictor of a trained model: `load_predictor(Path("models/fnn/30")).predict(df)`."""
    return Predictor(load_checkpoint(model_dir_or_file))
