"""Training the three model kinds, one per insertion angle, on the estimator's voltages only.

- `ls`: the paper's calibration matrix, eq. (1)-(2), F = C x fitted by least squares with no
  intercept (scipy's `lstsq`, as scikit-learn's `LinearRegression(fit_intercept=False)` does);
- `fnn`: the paper's feed-forward network, channels -> 20 -> 20 -> 3 (Sec. III-B), on the
  inputs of the current sample;
- `lstm`: an LSTM on the last `window` input samples of the same trial (Sec. VI), the first
  samples of a trial padded by repeating its first sample, predicting the force at the last one.

What a model reads (`x`) is its params' `inputs` (`pipeline.modelling.features`): raw volts as in
the paper, or the FSR conductance relative to the trial's rest reading, which transfers between
estimator units; the checkpoint records it.

Inputs and targets of the networks are standardised with the training split's statistics only.
Training is bit-for-bit deterministic: seeded initialisation and shuffling, deterministic
algorithms, one intra-op thread (`networks.TRAIN_THREADS`). torch and scipy are imported inside the
functions that need them.
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd

from pipeline.config import PARAMS_MODELS, FNNParams, LSParams, LSTMParams
from pipeline.logs import Log
from pipeline.modelling.checkpoint import FORMAT, ModelConfig, data_sha256
from pipeline.modelling.choice import Choice, choose_inputs
from pipeline.modelling.features import ModelInputs, inputs_for
from pipeline.modelling.inputs import column_stats, features_of, inputs_of, trial_codes
from pipeline.modelling.networks import build_network, deterministic_torch, exact_sqrt
from pipeline.modelling.predictor import Predictor
from pipeline.rig.frontend import Circuit
from pipeline.vocab import AXES, KINDS, channels_of, rate_hz

if TYPE_CHECKING:
    import torch

LSTSQ_CUTOFF = 1e-6  # relative singular-value cutoff: scikit-learn's LinearRegression `tol` default
LOSS_DEFINITION = "MSE of fx, fy, fz standardised by the training split's mean and std, averaged over axes"
ModelParams = LSParams | FNNParams | LSTMParams


def _angle_deg(frame: pd.DataFrame) -> float:
    if "angle_deg" not in frame.columns:
        return math.nan
    angles = pd.unique(frame["angle_deg"].dropna())
    if len(angles) != 1:
        raise ValueError(f"one model per angle: the training rows hold angles {sorted(angles)}")
    return float(angles[0])


def flatten(params: Sequence[torch.nn.Parameter]) -> torch.Tensor:
    """One buffer holding the values of `params`, each parameter now a view of its own slice (values
    unchanged). An elementwise update of every parameter (an optimizer step, a running average) is
    then one op on the buffer rather than one per parameter: the same arithmetic element for element,
    so the same bits, at a fraction of the per-op overhead that dominates these small networks."""
    import torch

    with torch.no_grad():
        flat = torch.cat([p.detach().reshape(-1) for p in params])
        offset = 0
        for p in params:
            p.data = flat[offset : offset + p.numel()].view_as(p)
            offset += p.numel()
    return flat


class Adam:
    """Adam (Kingma & Ba), the arithmetic of torch.optim.Adam's single-tensor CPU path op for op
    (L2 `weight_decay` added to the gradient, as there) but for an exact square root (`exact_sqrt`:
    torch's depends on the CPU); a test checks the two agree bit for bit given the same root. The
    parameters are `flatten`ed: each step is a few ops on one buffer, whatever the layer count.

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
        self.flat = flatten(self.params)
        self.lr, (self.beta1, self.beta2), self.eps, self.weight_decay = lr, betas, eps, weight_decay
        self.exp_avg = torch.zeros_like(self.flat)
        self.exp_avg_sq = torch.zeros_like(self.flat)
        self.steps = 0

    def zero_grad(self) -> None:
        for p in self.params:
            p.grad = None

    def step(self) -> None:
        import torch

        grads = [p.grad for p in self.params]
        if any(g is None for g in grads):  # every parameter of these networks is in the loss
            missing = [i for i, g in enumerate(grads) if g is None]
            raise ValueError(f"Adam: parameter(s) {missing} have no gradient; run backward() first")
        self.steps += 1
        bias_correction1 = 1 - self.beta1**self.steps
        bias_correction2_sqrt = (1 - self.beta2**self.steps) ** 0.5
        step_size = self.lr / bias_correction1
        with torch.no_grad():
            grad = torch.cat([g.reshape(-1) for g in grads])  # type: ignore[union-attr]
            if self.weight_decay != 0:
                grad = grad.add(self.flat, alpha=self.weight_decay)
            self.exp_avg.lerp_(grad, 1 - self.beta1)
            self.exp_avg_sq.mul_(self.beta2).addcmul_(grad, grad, value=1 - self.beta2)
            denom = exact_sqrt(self.exp_avg_sq).div_(bias_correction2_sqrt).add_(self.eps)
            self.flat.addcdiv_(self.exp_avg, denom, value=-step_size)


@dataclass
class TrainResult:
    """What `fit` returns: the checkpoint dict, the per-epoch history and the summary metrics."""

    checkpoint: dict[str, Any]
    history: list[dict[str, float]]
    metrics: dict[str, Any]
    predictor: Predictor = field(init=False)

    def __post_init__(self) -> None:
        self.predictor = Predictor(self.checkpoint)


def fit(
    kind: str,
    params: ModelParams,
    train: pd.DataFrame,
    val: pd.DataFrame | None = None,
    *,
    train_data_sha256: str | None = None,
    front_end: Circuit | None = None,
    other_designs: Sequence[str] = (),
    decided: Choice | None = None,
    log: Log | None = None,
) -> TrainResult:
    """Train one model of `kind` on `train`, early-stopping the networks on `val` (if it has rows).

    `train_data_sha256` identifies the data in the checkpoint; by default a hash of the frames.
    `front_end` is the circuit the training units declare, which the conductance inputs read through
    (ValueError if they need one and there is none); `other_designs`, the units the model must also
    serve that declare another circuit (then `inputs.kind: auto` chooses among the conductance kinds).
    With `inputs.kind: auto` each candidate is scored on this angle's rows, and the best is trained,
    or the kind `decided` for all the model kind's angles (the choose stage's), with this angle's
    scores beside it.
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
        if not frame.empty and (missing := [c for c in AXES if c not in frame.columns]):
            raise ValueError(f"the {name} rows lack the target column(s) {missing}")
    if not val.empty and channels_of(val) != channels:
        raise ValueError(f"validation channels {channels_of(val)} differ from training channels {channels}")

    log = log or (lambda _msg: None)
    _import_backends(kind)  # before the clock: train_seconds measures the work, not the imports
    codes = trial_codes(train)
    started = time.perf_counter()
    choice = None
    if params.inputs.kind == "auto":  # chosen by validation on this data (pipeline.modelling.choice)
        choice = choose(kind, params, train, val, front_end, other_designs)
        if decided is not None:  # one kind for all angles: this angle's own scores stay beside it
            choice = replace(choice, chosen=decided.chosen, folds=decided.folds)
    if choice is not None:
        only = f", among {choice.only}" if choice.only else ""
        log(f"inputs by validation ({choice.folds}{only}): {choice.chosen}; mean NRMSE % {choice.scores}")
    elif other_designs and front_end is not None and not params.inputs.kind.endswith("conductance"):
        who = ", ".join(other_designs)
        log(f"warning: {who}: another circuit declared, which {params.inputs.kind} inputs cannot read")
    spec = inputs_for(choice.chosen if choice else params.inputs.kind, params.inputs.rest_s, front_end)
    if isinstance(params, LSParams):
        cfg = ModelConfig(kind="ls", n_in=len(channels))
        state, pre, history, summary = _fit_ls(params, spec, train, val, channels)
    else:
        if isinstance(params, FNNParams):
            cfg = ModelConfig("fnn", len(channels), hidden=tuple(params.hidden), activation=params.activation)
        else:
            hidden = (params.hidden,) * params.layers
            cfg = ModelConfig("lstm", len(channels), hidden=hidden, activation="tanh", window=params.window)
        state, pre, history, summary = _fit_network(cfg, params, spec, train, val, channels, log)

    seconds = time.perf_counter() - started
    sha = train_data_sha256 or data_sha256(train, val)
    checkpoint = {
        "format": FORMAT,
        "kind": kind,
        "config": cfg.to_dict(),
        "state_dict": state,
        "preprocessing": pre,
        "channels": list(channels),
        "inputs": spec.model_dump(mode="json"),
        "inputs_choice": None if choice is None else choice.to_dict(),  # None: pinned in params
        "targets": list(AXES),
        "rate_hz": rate_hz(train["t_s"], codes) if "t_s" in train.columns else math.nan,
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
        "inputs": spec.kind,
        "inputs_choice": None if choice is None else choice.to_dict(),
        "train_seconds": round(seconds, 3),
        "n_train": len(train),
        "n_val": len(val),
        "train_data_sha256": sha,
    }
    return TrainResult(checkpoint, history, metrics)


def choose(
    kind: str,
    params: ModelParams,
    train: pd.DataFrame,
    val: pd.DataFrame,
    front_end: Circuit | None,
    other_designs: Sequence[str] = (),
) -> Choice:
    """`choose_inputs` for one angle's rows with the model's own settings (the LSTM's window, least
    squares' intercept)."""
    window = params.window if isinstance(params, LSTMParams) else 1
    intercept = params.fit_intercept if isinstance(params, LSParams) else True
    rest_s, channels = params.inputs.rest_s, channels_of(train)
    return choose_inputs(kind, train, val, channels, front_end, rest_s, window, intercept, other_designs)


def _import_backends(kind: str) -> None:
    import torch  # noqa: F401

    if kind == "ls":
        import scipy.linalg  # noqa: F401


def _torch_version() -> str:
    import torch

    return str(torch.__version__)


def _scaled_mse(pred: np.ndarray, y: np.ndarray, y_std: np.ndarray) -> float:
    return float(np.mean(((pred - y) / y_std) ** 2)) if len(y) else math.nan


def _fit_ls(
    params: LSParams, spec: ModelInputs, train: pd.DataFrame, val: pd.DataFrame, channels: list[str]
) -> tuple[dict[str, Any], dict[str, Any], list[dict[str, float]], dict[str, Any]]:
    """Eq. (2) on the unscaled inputs: that is the paper's method, and scaling would add an offset."""
    import torch

    x = features_of(train, channels, spec)
    y = train[list(AXES)].to_numpy(np.float64)
    _, y_std = column_stats(y)  # only to report a loss on the same scale as the networks'
    weight, bias = _least_squares(x, y, params.fit_intercept)
    train_loss = _scaled_mse(x @ weight.T + bias, y, y_std)
    if val.empty:
        val_loss = math.nan
    else:
        xv = features_of(val, channels, spec)
        val_loss = _scaled_mse(xv @ weight.T + bias, val[list(AXES)].to_numpy(np.float64), y_std)
    state = {"weight": torch.from_numpy(weight), "bias": torch.from_numpy(bias)}
    n = len(channels)
    pre = _preprocessing(np.zeros(n), np.ones(n), np.zeros(len(AXES)), np.ones(len(AXES)))
    history = [{"epoch": 1, "train_loss": train_loss, "val_loss": val_loss}]
    summary = {
        "epochs_run": 1,
        "best_epoch": 1,
        "best_val_loss": None if math.isnan(val_loss) else val_loss,
        "early_stopping": False,
    }
    return state, pre, history, summary


def _least_squares(x: np.ndarray, y: np.ndarray, intercept: bool) -> tuple[np.ndarray, np.ndarray]:
    """(weight, bias) of y ~ x @ weight.T + bias: scikit-learn's `LinearRegression(fit_intercept=
    intercept)`, step for step (centre with an intercept, then LAPACK's gelsd with its default
    cutoff), so the same bytes; without importing scikit-learn, which took ~1.5 s of each ls stage."""
    from scipy import linalg

    x_offset = x.mean(axis=0) if intercept else np.zeros(x.shape[1])
    y_offset = y.mean(axis=0) if intercept else np.zeros(y.shape[1])
    coef, *_ = linalg.lstsq(x - x_offset, y - y_offset, cond=LSTSQ_CUTOFF)
    weight = np.array(coef.T, dtype=np.float64)  # a copy: not a view into lstsq's work array
    return weight, y_offset - x_offset @ weight.T


def _preprocessing(x_mean: np.ndarray, x_std: np.ndarray, y_mean: np.ndarray, y_std: np.ndarray) -> dict:
    import torch

    arrays = {"x_mean": x_mean, "x_std": x_std, "y_mean": y_mean, "y_std": y_std}
    return {k: torch.tensor(np.asarray(v, dtype=np.float64)) for k, v in arrays.items()}


def _fit_network(
    cfg: ModelConfig,
    params: FNNParams | LSTMParams,
    spec: ModelInputs,
    train: pd.DataFrame,
    val: pd.DataFrame,
    channels: list[str],
    log: Log,
) -> tuple[dict[str, Any], dict[str, Any], list[dict[str, float]], dict[str, Any]]:
    """Adam on standardised data, seeded shuffling, early stopping on val MSE keeping the best weights."""
    import torch

    x_mean, x_std = column_stats(features_of(train, channels, spec))
    y_mean, y_std = column_stats(train[list(AXES)].to_numpy(np.float64))
    x_tr = torch.from_numpy(inputs_of(cfg, train, channels, x_mean, x_std, spec))
    y_tr = torch.from_numpy(((train[list(AXES)].to_numpy(np.float64) - y_mean) / y_std).astype(np.float32))
    has_val = not val.empty
    if has_val:
        x_va = torch.from_numpy(inputs_of(cfg, val, channels, x_mean, x_std, spec))
        y_va = torch.from_numpy(((val[list(AXES)].to_numpy(np.float64) - y_mean) / y_std).astype(np.float32))
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
    return best_state, _preprocessing(x_mean, x_std, y_mean, y_std), history, summary
