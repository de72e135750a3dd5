"""Force models of the `train` stage and the predictor that serves them.

Three kinds, one model per insertion angle, all reading the estimator's voltages only (never a
measured force, so every one of them is deployable on the simulator):

- `ls`: the paper's calibration matrix, eq. (1)-(2), F = C v fitted by least squares on raw
  volts with no intercept (scikit-learn `LinearRegression(fit_intercept=False)`);
- `fnn`: the paper's feed-forward network, channels -> 20 -> 20 -> 3 (Sec. III-B), on the
  voltages of the current sample;
- `lstm`: an LSTM on the last `window` voltage samples of the same trial (Sec. VI), the first
  samples of a trial padded by repeating its first sample, predicting the force at the last one.

Inputs and targets of the networks are standardised with the training split's statistics only.
Training is bit-for-bit deterministic: seeded initialisation and shuffling, deterministic
algorithms, one intra-op thread (`TRAIN_THREADS`).

A checkpoint (`model.pt`) is a plain dict of tensors, strings, numbers, lists and dicts, so
`torch.load(path, weights_only=True)` reads it (no pickled objects):
  format "needlecue-model/1"; kind "ls" | "fnn" | "lstm"; config `ModelConfig.to_dict()`;
  state_dict (ls: "weight" (3, channels) = C of eq. (1) and "bias" (3,), zeros without intercept;
  networks: their module's state_dict); preprocessing {x_mean, x_std, y_mean, y_std} float64
  (identity for ls); channels; targets ["fx", "fy", "fz"]; rate_hz; angle_deg;
  train_data_sha256; params (the params section it was trained with); torch_version.

torch and scikit-learn are imported inside the functions that need them, so importing this module
(for its params models, say) stays cheap.
"""

from __future__ import annotations

import functools
import hashlib
import math
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Literal

import numpy as np
import pandas as pd
from pydantic import Field

from pipeline.config import Section

if TYPE_CHECKING:
    import torch

FORMAT = "needlecue-model/1"
CHECKPOINT_FILE = "model.pt"
KINDS = ("ls", "fnn", "lstm")
TARGETS = ("fx", "fy", "fz")
# Every other column of a processed split file is an estimator channel, in file order.
NON_CHANNELS = frozenset({"batch_id", "trial_id", "angle_deg", "tissue_point", "t_s", "phase", *TARGETS})
# One intra-op thread: on these tiny layers two threads were 15-20 % slower (measured on the 2-core
# CI box, which other jobs share), and a fixed count keeps the order of float reductions, hence the
# weights, the same on any machine (1 and 2 threads happen to agree at the default sizes; larger
# layers cross torch's parallel grain and would not).
TRAIN_THREADS = 1
PREDICT_CHUNK = 65_536  # rows per forward pass at prediction time
LOSS_DEFINITION = "MSE of fx, fy, fz standardised by the training split's mean and std, averaged over axes"

Log = Callable[[str], None]


# --- params (one section of params.yaml each) --------------------------------------------------


class LSParams(Section):
    """`ls`: the calibration matrix of eq. (1)-(2)."""

    fit_intercept: bool = False  # the paper's F = C v has none; zero volts -> zero force


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


ModelParams = LSParams | FNNParams | LSTMParams
PARAMS_MODELS: dict[str, type[Section]] = {"ls": LSParams, "fnn": FNNParams, "lstm": LSTMParams}


# --- architecture ------------------------------------------------------------------------------


@dataclass(frozen=True)
class ModelConfig:
    """Everything needed to rebuild a model's modules from its state_dict (cf. nanoGPT's GPTConfig).

    `hidden` lists the widths of the hidden layers: () for `ls`, (20, 20) for the paper's FNN,
    (hidden,) * layers for the stacked LSTM. `window` is 1 for the memoryless models.
    """

    kind: str
    n_in: int
    n_out: int = 3
    hidden: tuple[int, ...] = ()
    activation: str = "identity"  # fnn: tanh | relu; lstm: tanh (inside its cell); ls: identity
    window: int = 1

    def to_dict(self) -> dict[str, Any]:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ModelConfig:
        return cls(**{**d, "hidden": tuple(d["hidden"])})


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


def build_network(cfg: ModelConfig) -> torch.nn.Module:
    """The torch module of an `fnn` or `lstm` config (float32, freshly initialised)."""
    from collections import OrderedDict

    from torch import nn

    if cfg.kind == "fnn":
        act = {"tanh": nn.Tanh, "relu": nn.ReLU}[cfg.activation]
        layers: OrderedDict[str, nn.Module] = OrderedDict()
        width = cfg.n_in
        for i, h in enumerate(cfg.hidden, start=1):
            layers[f"fc{i}"] = nn.Linear(width, h)
            layers[f"act{i}"] = act()
            width = h
        layers["out"] = nn.Linear(width, cfg.n_out)
        return nn.Sequential(layers)
    if cfg.kind == "lstm":
        if len(set(cfg.hidden)) != 1:
            raise ValueError(f"an LSTM's layers share one width, got hidden={cfg.hidden}")
        return _lstm_class()(cfg)
    raise ValueError(f"no network for model kind {cfg.kind!r}")


# --- data --------------------------------------------------------------------------------------


def channels_of(frame: pd.DataFrame) -> list[str]:
    """The estimator channels of a processed split frame: every non-id, non-force column, in order."""
    return [str(c) for c in frame.columns if c not in NON_CHANNELS]


def _trial_codes(frame: pd.DataFrame) -> np.ndarray:
    """An integer per row naming its (batch_id, trial_id); a frame without them is one trial."""
    keys = [c for c in ("batch_id", "trial_id") if c in frame.columns]
    if not keys or frame.empty:
        return np.zeros(len(frame), dtype=np.int64)
    return frame.groupby(keys, sort=False, dropna=False).ngroup().to_numpy(np.int64)


def sequence_order(codes: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows sorted by (trial, t) and, per sorted row, the sorted position where its trial begins.

    The sort is stable, so rows of one trial with equal (or no) times keep their given order.
    """
    order = np.lexsort((t, codes))
    c = codes[order]
    n = len(c)
    begins = np.ones(n, dtype=bool)
    begins[1:] = c[1:] != c[:-1]
    start = np.maximum.accumulate(np.where(begins, np.arange(n), 0)) if n else np.zeros(0, np.int64)
    return order, start


def window_index(start: np.ndarray, window: int) -> np.ndarray:
    """(n, window) positions of each row's window in trial order: the last `window` rows of its own
    trial ending at the row itself, positions before the trial's start clamped to its first row
    (padding by repetition), so a window never reaches into another trial."""
    n = len(start)
    idx = np.arange(n)[:, None] - (window - 1) + np.arange(window)[None, :]
    return np.maximum(idx, start[:, None])


def data_sha256(*frames: pd.DataFrame) -> str:
    """Content hash of in-memory frames (used when a model is not trained from files)."""
    h = hashlib.sha256()
    for f in frames:
        h.update(pd.util.hash_pandas_object(f, index=False).to_numpy().tobytes())
        h.update(b"\0")
    return h.hexdigest()


def file_sha256(paths: Sequence[Path]) -> str:
    """SHA-256 of the concatenated bytes of files (the train and val parquet files, a model.onnx)."""
    h = hashlib.sha256()
    for p in paths:
        h.update(Path(p).read_bytes())
    return h.hexdigest()


def _rate_hz(frame: pd.DataFrame, codes: np.ndarray) -> float:
    """The sampling rate of the grid: 1 / median time step within trials (nan if unknown)."""
    if "t_s" not in frame.columns or len(frame) < 2:
        return math.nan
    t = frame["t_s"].to_numpy(np.float64)
    order = np.lexsort((t, codes))
    dt = np.diff(t[order])[codes[order][1:] == codes[order][:-1]]
    dt = dt[dt > 0]
    return float(1.0 / np.median(dt)) if len(dt) else math.nan


def _angle_deg(frame: pd.DataFrame) -> float:
    if "angle_deg" not in frame.columns:
        return math.nan
    angles = pd.unique(frame["angle_deg"].dropna())
    if len(angles) != 1:
        raise ValueError(f"one model per angle: the training rows hold angles {sorted(angles)}")
    return float(angles[0])


# --- training ----------------------------------------------------------------------------------


def _set_deterministic(mode: bool, warn_only: bool = False) -> None:
    """`torch.use_deterministic_algorithms`, minus its import of torch._inductor (~0.95 s measured, per
    process) when inductor is not loaded: that import only sets inductor's own flag, which matters
    for torch.compile alone, unused here. With inductor loaded, the public call keeps both in step."""
    import sys

    import torch

    setter = getattr(torch._C, "_set_deterministic_algorithms", None)
    if setter is None or "torch._inductor.config" in sys.modules:
        torch.use_deterministic_algorithms(mode, warn_only=warn_only)
    else:
        setter(mode, warn_only=warn_only)


@contextmanager
def deterministic_torch(seed: int | None = None, threads: int | None = None) -> Iterator[None]:
    """Fixed thread count, deterministic algorithms and (optionally) a seeded global RNG, all
    restored on exit so a caller's own torch state is untouched."""
    import torch

    prev_threads = torch.get_num_threads()
    prev_det = torch.are_deterministic_algorithms_enabled()
    prev_warn = torch.is_deterministic_algorithms_warn_only_enabled()
    torch.set_num_threads(threads or TRAIN_THREADS)
    _set_deterministic(True)
    try:
        with torch.random.fork_rng(devices=[]):
            if seed is not None:
                torch.manual_seed(seed)
            yield
    finally:
        _set_deterministic(prev_det, warn_only=prev_warn)
        torch.set_num_threads(prev_threads)


class Adam:
    """Adam (Kingma & Ba), the arithmetic of torch.optim.Adam's single-tensor CPU path op for op
    (L2 `weight_decay` added to the gradient, as there); a test checks the two agree bit for bit.

    Why not torch.optim.Adam itself: every torch.optim optimizer imports torch._dynamo on first
    use (~1 s measured per process, for torch.compile support unused here), and the 12 network
    stages each pay it; this one needs only tensor ops.
    """

    def __init__(
        self,
        params: Iterator[torch.nn.Parameter] | Sequence[torch.nn.Parameter],
        lr: float,
        betas: tuple[float, float] = (0.9, 0.999),
        eps: float = 1e-8,
        weight_decay: float = 0.0,
    ) -> None:
        import torch

        self.params = list(params)
        self.lr, (self.beta1, self.beta2), self.eps, self.weight_decay = lr, betas, eps, weight_decay
        self.exp_avg = [torch.zeros_like(p, memory_format=torch.preserve_format) for p in self.params]
        self.exp_avg_sq = [torch.zeros_like(p, memory_format=torch.preserve_format) for p in self.params]
        self.steps = 0

    def zero_grad(self) -> None:
        for p in self.params:
            p.grad = None

    def step(self) -> None:
        import torch

        self.steps += 1
        bias_correction1 = 1 - self.beta1**self.steps
        bias_correction2_sqrt = (1 - self.beta2**self.steps) ** 0.5
        step_size = self.lr / bias_correction1
        with torch.no_grad():
            for p, exp_avg, exp_avg_sq in zip(self.params, self.exp_avg, self.exp_avg_sq, strict=True):
                if p.grad is None:
                    continue
                grad = p.grad if self.weight_decay == 0 else p.grad.add(p, alpha=self.weight_decay)
                exp_avg.lerp_(grad, 1 - self.beta1)
                exp_avg_sq.mul_(self.beta2).addcmul_(grad, grad, value=1 - self.beta2)
                denom = (exp_avg_sq.sqrt() / bias_correction2_sqrt).add_(self.eps)
                p.addcdiv_(exp_avg, denom, value=-step_size)


@dataclass
class TrainResult:
    """What `fit` returns: the checkpoint dict, the per-epoch history and the summary metrics."""

    checkpoint: dict[str, Any]
    history: list[dict[str, float]]
    metrics: dict[str, Any]
    predictor: Predictor = field(init=False)

    def __post_init__(self) -> None:
        self.predictor = Predictor(self.checkpoint)


def _stats(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Column mean and population std; a constant column gets std 1 (it would divide by zero)."""
    mean = a.mean(axis=0)
    std = a.std(axis=0)
    return mean, np.where(std > 0, std, 1.0)


def fit(
    kind: str,
    params: ModelParams,
    train: pd.DataFrame,
    val: pd.DataFrame | None = None,
    *,
    train_data_sha256: str | None = None,
    log: Log | None = None,
) -> TrainResult:
    """Train one model of `kind` on `train`, early-stopping the networks on `val` (if it has rows).

    `train_data_sha256` identifies the data in the checkpoint; by default a hash of the frames.
    """
    if kind not in KINDS:
        raise ValueError(f"unknown model kind {kind!r}; expected one of {', '.join(KINDS)}")
    if not isinstance(params, PARAMS_MODELS[kind]):
        raise TypeError(f"{kind} takes {PARAMS_MODELS[kind].__name__}, got {type(params).__name__}")
    if train.empty:
        raise ValueError("no training rows")
    val = train.iloc[:0] if val is None else val
    channels = channels_of(train)
    if not channels:
        raise ValueError(f"the training rows have no estimator channel (columns: {list(train.columns)})")
    for name, frame in (("training", train), ("validation", val)):
        if not frame.empty and (missing := [c for c in TARGETS if c not in frame.columns]):
            raise ValueError(f"the {name} rows lack the target column(s) {missing}")
    if not val.empty and channels_of(val) != channels:
        raise ValueError(f"validation channels {channels_of(val)} differ from training channels {channels}")

    log = log or (lambda _msg: None)
    _import_backends(kind)  # before the clock: train_seconds measures the work, not the imports
    codes = _trial_codes(train)
    started = time.perf_counter()
    if isinstance(params, LSParams):
        cfg = ModelConfig(kind="ls", n_in=len(channels))
        state, pre, history, summary = _fit_ls(params, train, val, channels)
    else:
        if isinstance(params, FNNParams):
            cfg = ModelConfig("fnn", len(channels), hidden=tuple(params.hidden), activation=params.activation)
        else:
            hidden = (params.hidden,) * params.layers
            cfg = ModelConfig("lstm", len(channels), hidden=hidden, activation="tanh", window=params.window)
        state, pre, history, summary = _fit_network(cfg, params, train, val, channels, log)

    seconds = time.perf_counter() - started
    sha = train_data_sha256 or data_sha256(train, val)
    checkpoint = {
        "format": FORMAT,
        "kind": kind,
        "config": cfg.to_dict(),
        "state_dict": state,
        "preprocessing": pre,
        "channels": list(channels),
        "targets": list(TARGETS),
        "rate_hz": _rate_hz(train, codes),
        "angle_deg": _angle_deg(train),
        "train_data_sha256": sha,
        "params": params.model_dump(mode="json"),
        "torch_version": _torch_version(),
    }
    metrics = {
        "kind": kind,
        "angle_deg": checkpoint["angle_deg"],
        **summary,
        "loss": LOSS_DEFINITION,
        "train_seconds": round(seconds, 3),
        "n_train": len(train),
        "n_val": len(val),
        "train_data_sha256": sha,
    }
    return TrainResult(checkpoint, history, metrics)


def _import_backends(kind: str) -> None:
    import torch  # noqa: F401

    if kind == "ls":
        import sklearn.linear_model  # noqa: F401


def _torch_version() -> str:
    import torch

    return str(torch.__version__)


def _scaled_mse(pred: np.ndarray, y: np.ndarray, y_std: np.ndarray) -> float:
    return float(np.mean(((pred - y) / y_std) ** 2)) if len(y) else math.nan


def _fit_ls(
    params: LSParams, train: pd.DataFrame, val: pd.DataFrame, channels: list[str]
) -> tuple[dict[str, Any], dict[str, Any], list[dict[str, float]], dict[str, Any]]:
    """Eq. (2) on raw volts, no scaling: that is the paper's method, and scaling would add an offset."""
    import torch
    from sklearn.linear_model import LinearRegression

    x = train[channels].to_numpy(np.float64)
    y = train[list(TARGETS)].to_numpy(np.float64)
    _, y_std = _stats(y)  # only to report a loss on the same scale as the networks'

    reg = LinearRegression(fit_intercept=params.fit_intercept).fit(x, y)
    # copies: coef_ can be a view into lstsq's n_samples-long work array, which torch.save would store whole
    weight = np.array(reg.coef_, dtype=np.float64).reshape(len(TARGETS), len(channels))
    bias = np.asarray(reg.intercept_, dtype=np.float64) * np.ones(len(TARGETS))
    train_loss = _scaled_mse(x @ weight.T + bias, y, y_std)
    if val.empty:
        val_loss = math.nan
    else:
        xv = val[channels].to_numpy(np.float64)
        val_loss = _scaled_mse(xv @ weight.T + bias, val[list(TARGETS)].to_numpy(np.float64), y_std)
    state = {"weight": torch.from_numpy(weight), "bias": torch.from_numpy(bias)}
    n = len(channels)
    pre = _preprocessing(np.zeros(n), np.ones(n), np.zeros(len(TARGETS)), np.ones(len(TARGETS)))
    history = [{"epoch": 1, "train_loss": train_loss, "val_loss": val_loss}]
    summary = {
        "epochs_run": 1,
        "best_epoch": 1,
        "best_val_loss": None if math.isnan(val_loss) else val_loss,
        "early_stopping": False,
    }
    return state, pre, history, summary


def _preprocessing(x_mean: np.ndarray, x_std: np.ndarray, y_mean: np.ndarray, y_std: np.ndarray) -> dict:
    import torch

    arrays = {"x_mean": x_mean, "x_std": x_std, "y_mean": y_mean, "y_std": y_std}
    return {k: torch.tensor(np.asarray(v, dtype=np.float64)) for k, v in arrays.items()}


def _inputs(
    cfg: ModelConfig, frame: pd.DataFrame, channels: list[str], x_mean: np.ndarray, x_std: np.ndarray
) -> np.ndarray:
    """Standardised float32 network inputs of a frame's rows, in the frame's order."""
    x = (frame[channels].to_numpy(np.float64) - x_mean) / x_std
    t = frame["t_s"].to_numpy(np.float64) if "t_s" in frame.columns else np.arange(len(frame), dtype=float)
    return _network_inputs(cfg, x, _trial_codes(frame), t)


def _network_inputs(cfg: ModelConfig, x_std: np.ndarray, codes: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(n, c) for the FNN; (n, window, c) for the LSTM, each row's window built within its trial."""
    if cfg.kind != "lstm":
        return x_std.astype(np.float32)
    order, start = sequence_order(codes, t)
    windows = x_std[order][window_index(start, cfg.window)]  # sorted rows' windows
    out = np.empty_like(windows)
    out[order] = windows  # back to the frame's row order
    return out.astype(np.float32)


def _fit_network(
    cfg: ModelConfig,
    params: FNNParams | LSTMParams,
    train: pd.DataFrame,
    val: pd.DataFrame,
    channels: list[str],
    log: Log,
) -> tuple[dict[str, Any], dict[str, Any], list[dict[str, float]], dict[str, Any]]:
    """Adam on standardised data, seeded shuffling, early stopping on val MSE keeping the best weights."""
    import torch

    x_mean, x_std = _stats(train[channels].to_numpy(np.float64))
    y_mean, y_std = _stats(train[list(TARGETS)].to_numpy(np.float64))
    x_tr = torch.from_numpy(_inputs(cfg, train, channels, x_mean, x_std))
    y_tr = torch.from_numpy(((train[list(TARGETS)].to_numpy(np.float64) - y_mean) / y_std).astype(np.float32))
    has_val = not val.empty
    if has_val:
        x_va = torch.from_numpy(_inputs(cfg, val, channels, x_mean, x_std))
        y_va = torch.from_numpy(
            ((val[list(TARGETS)].to_numpy(np.float64) - y_mean) / y_std).astype(np.float32)
        )
    else:
        log(f"no validation rows: no early stopping, training all {params.max_epochs} epochs")

    n, bs = len(x_tr), params.batch_size
    every = max(1, params.max_epochs // 10)
    history: list[dict[str, float]] = []
    with deterministic_torch(params.seed):
        net = build_network(cfg)  # initialised from the seeded (forked) global RNG
        gen = torch.Generator().manual_seed(params.seed)
        opt = Adam(net.parameters(), lr=params.lr, weight_decay=params.weight_decay)
        loss_fn = torch.nn.MSELoss()
        # The averaged copy is what gets validated and saved: it smooths the step-to-step noise of
        # the SGD iterate, so the early-stopping choice depends less on where one epoch happened to end.
        avg = build_network(cfg) if params.ema > 0 else net
        if params.ema > 0:
            avg.load_state_dict(net.state_dict())
            pairs = list(zip(avg.parameters(), net.parameters(), strict=True))
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
                        for a, w in pairs:
                            a.lerp_(w, 1 - params.ema)
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
    return best_state, _preprocessing(x_mean, x_std, y_mean, y_std), history, summary


# --- checkpoint and predictor ------------------------------------------------------------------


def save_checkpoint(checkpoint: dict[str, Any], path: Path) -> None:
    """`torch.save` of the plain dict (loadable with weights_only=True)."""
    import torch

    Path(path).parent.mkdir(parents=True, exist_ok=True)
    torch.save(checkpoint, path)


class Predictor:
    """A trained model behind one call: volts in, force in newtons out.

    Attributes: `kind`, `channels` (the order it reads them in), `targets`, `rate_hz`,
    `angle_deg`, `window` (samples of history it uses, 1 for ls/fnn), `config`, `checkpoint`.
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

    def predict(self, frame: pd.DataFrame) -> np.ndarray:
        """Forces (n, 3) in N for the frame's rows, in its row order.

        Reads the model's channels by name (extra columns are ignored). The LSTM builds its windows
        per (batch_id, trial_id) in t_s order; a frame without those columns is one trial in row order.
        """
        missing = [c for c in self.channels if c not in frame.columns]
        if missing:
            raise ValueError(
                f"the frame lacks the model's channel(s) {missing}: this {self.kind} model "
                f"(angle {self.angle_deg:g}°) reads {list(self.channels)}; "
                f"the frame has {list(frame.columns)}"
            )
        volts = frame[list(self.channels)].to_numpy(np.float64)
        t = (
            frame["t_s"].to_numpy(np.float64)
            if "t_s" in frame.columns
            else np.arange(len(frame), dtype=float)
        )
        return self._predict(volts, _trial_codes(frame), t)

    def predict_arrays(
        self, volts: np.ndarray, trial_ids: Sequence[Any] | np.ndarray | None = None
    ) -> np.ndarray:
        """Forces (n, 3) in N for volts (n, channels) in `self.channels` order, rows in time order
        within each trial; `trial_ids` (n,) labels trials, None = all rows are one trial.

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
        return self._predict(volts, codes.astype(np.int64), np.arange(len(volts), dtype=float))

    def _predict(self, volts: np.ndarray, codes: np.ndarray, t: np.ndarray) -> np.ndarray:
        if not np.isfinite(volts).all():
            bad = [c for c, ok in zip(self.channels, np.isfinite(volts).all(axis=0), strict=True) if not ok]
            raise ValueError(f"non-finite volts in channel(s) {bad}")
        if len(volts) == 0:
            return np.zeros((0, len(self.targets)))
        if self.kind == "ls":
            return volts @ self._weight.T + self._bias
        import torch

        x = torch.from_numpy(_network_inputs(self.config, (volts - self._x_mean) / self._x_std, codes, t))
        with deterministic_torch(), torch.no_grad():  # same thread count as training: same float sums
            # fixed-size chunks bound the memory of long recordings (an LSTM keeps every step's state)
            y = torch.cat([self._net(x[i : i + PREDICT_CHUNK]) for i in range(0, len(x), PREDICT_CHUNK)])
        return y.double().numpy() * self._y_std + self._y_mean


def load_checkpoint(model_dir_or_file: Path) -> dict[str, Any]:
    """The checkpoint dict of a model folder (its `model.pt`) or file, loaded with weights_only=True."""
    import torch

    path = Path(model_dir_or_file)
    if path.is_dir():
        path = path / CHECKPOINT_FILE
    if not path.is_file():
        raise FileNotFoundError(f"no model checkpoint at {path}")
    return torch.load(path, map_location="cpu", weights_only=True)


def load_predictor(model_dir_or_file: Path) -> Predictor:
    """The predictor of a trained model: `load_predictor(Path("models/fnn/30")).predict(df)`."""
    return Predictor(load_checkpoint(model_dir_or_file))
