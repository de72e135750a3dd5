"""Deployable force models: a needlecue checkpoint as a self-contained ONNX graph, logged to MLflow.

The graph reads the model's inputs and returns newtons, with the checkpoint's standardisation inside
it, so the simulator's client needs onnxruntime, numpy and `pipeline.modelling.features` (which turns
volts into inputs, and applies a unit's calibration) and never a pickle:

    input  `inputs`  float32 (N, C) for ls/fnn, (N, window, C) for lstm, in `channels` order
    output `force_n` float32 (N, 3): fx, fy, fz in N

The same checkpoint gives the same ONNX bytes, in any process (a test checks it), and the MLflow model
carries a `needlecue` metadata block (`deploy_metadata`) with everything the client needs to feed it.
What a simulator runs is verified as one (`pipeline.client.folder`): the graph's own metadata holds
the sha256 of that block, and the block the sha256 of the graph (`onnx_sha256`), both recorded when
the model is logged.

torch, onnx and mlflow are imported inside the functions, so importing this module is cheap.
"""

from __future__ import annotations

import hashlib
import io
import json
import math
import warnings
from typing import TYPE_CHECKING, Any

import numpy as np

from pipeline.modelling.checkpoint import ModelConfig, check_checkpoint, checkpoint_sha256
from pipeline.modelling.features import spec_of
from pipeline.modelling.networks import build_network
from pipeline.vocab import DEPLOY_FORMAT, INPUT_NAME, OUTPUT_NAME, description_sha256

if TYPE_CHECKING:
    import torch
    from mlflow.models.model import ModelInfo

# Pinned rather than the exporter's default, so a torch upgrade does not silently change the graph;
# 17 is the newest opset the legacy exporter handles fully and onnxruntime >= 1.15 runs it.
OPSET = 17
BATCH_DIM = "batch"
# The legacy (TorchScript) exporter is the one that handles nn.LSTM without onnxscript; these are the
# warnings it raises about itself, not about our model, so they are silenced and nothing else is.
_EXPORTER_NOISE = (
    "You are using the legacy TorchScript-based ONNX export",
    "The feature will be removed",
    # nn.LSTM without explicit h0/c0: the exporter builds zero states from the input's batch size,
    # which is correct for any batch (a test runs batches of 1 and many).
    "Exporting a model to ONNX with a batch_size other than 1",
)


def deployable_module(checkpoint: dict[str, Any]) -> torch.nn.Module:
    """The checkpoint's network as one float32 module, model inputs in, newtons out (eval mode)."""
    import torch
    from torch import nn

    check_checkpoint(checkpoint, "export")
    cfg = ModelConfig.from_dict(checkpoint["config"])
    state = checkpoint["state_dict"]
    with torch.random.fork_rng(devices=[]):  # the throwaway initialisation must not use the caller's RNG
        if cfg.kind == "ls":
            # F = C x (+ b): the paper's calibration matrix on the unscaled inputs (as Predictor does)
            net: nn.Module = nn.Linear(cfg.n_in, cfg.n_out)
            net.load_state_dict({k: state[k].float() for k in ("weight", "bias")})
        else:
            net = build_network(cfg)
            net.load_state_dict(state)
    pre = None if cfg.kind == "ls" else checkpoint["preprocessing"]

    class Deployable(nn.Module):
        """(volts - x_mean) / x_std -> net -> * y_std + y_mean, in float32."""

        def __init__(self) -> None:
            super().__init__()
            self.net = net
            self.scaled = pre is not None
            if pre is not None:
                for key in ("x_mean", "x_std", "y_mean", "y_std"):
                    self.register_buffer(key, pre[key].float().clone())

        def forward(self, volts: torch.Tensor) -> torch.Tensor:
            if not self.scaled:
                return self.net(volts)
            return self.net((volts - self.x_mean) / self.x_std) * self.y_std + self.y_mean

    return Deployable().float().eval()


def to_onnx(checkpoint: dict[str, Any], description: str | None = None) -> bytes:
    """The serialized ONNX model of a checkpoint (see the module docstring for its input and output);
    `description`: the sha256 of the description it is logged with (`description_sha256`)."""
    import onnx
    import torch

    module = deployable_module(checkpoint)
    cfg = ModelConfig.from_dict(checkpoint["config"])
    n_in = len(checkpoint["channels"])
    # a batch of 2 in the trace: no dimension of size 1 the exporter might specialise on
    dummy = torch.zeros((2, cfg.window, n_in) if cfg.kind == "lstm" else (2, n_in))
    buffer = io.BytesIO()
    with warnings.catch_warnings(), torch.no_grad():
        for message in _EXPORTER_NOISE:
            warnings.filterwarnings("ignore", message=message)
        # nn.LSTM's own shape checks turn tensors into Python bools while tracing: harmless here
        warnings.filterwarnings("ignore", category=torch.jit.TracerWarning)
        torch.onnx.export(
            module,
            (dummy,),
            buffer,
            dynamo=False,
            opset_version=OPSET,
            input_names=[INPUT_NAME],
            output_names=[OUTPUT_NAME],
            dynamic_axes={INPUT_NAME: {0: BATCH_DIM}, OUTPUT_NAME: {0: BATCH_DIM}},
            do_constant_folding=True,
        )
    proto = onnx.load_from_string(buffer.getvalue())
    # The graph alone says what it is: whoever finds a bare model.onnx can still feed it correctly.
    keys = ("format", "kind", "angle_deg", "channels", "targets", "rate_hz", "window", "checkpoint_sha256")
    info = {k: v for k, v in deploy_metadata(checkpoint, None).items() if k in keys}
    if description is not None:
        info["description_sha256"] = description
    del proto.metadata_props[:]
    proto.metadata_props.add(key="needlecue", value=json.dumps(info, sort_keys=True))
    proto.producer_name, proto.doc_string = "needlecue", ""
    for node in proto.graph.node:  # no source locations of the exporting machine in the bytes
        node.doc_string = ""
    onnx.checker.check_model(proto, full_check=True)
    return proto.SerializeToString(deterministic=True)


def _json_float(value: Any) -> float | None:
    """A float, or None for nan (JSON and YAML readers disagree about nan)."""
    x = float(value)
    return None if math.isnan(x) else x


def _jsonable(value: Any, what: str) -> Any:
    """`value` round-tripped through strict JSON: the MLmodel file must hold plain data only."""
    try:
        return json.loads(json.dumps(value, allow_nan=False))
    except (TypeError, ValueError) as e:
        raise ValueError(f"{what} is not plain JSON data (numbers, strings, lists, dicts): {e}") from e


def deploy_metadata(checkpoint: dict[str, Any], cue_pack: dict[str, Any] | None) -> dict[str, Any]:
    """The `needlecue` block stored in the MLflow model's metadata: what the client needs to feed the
    graph and to cue a trainee, and where the model came from."""
    check_checkpoint(checkpoint, "export")
    return {
        "format": DEPLOY_FORMAT,
        "kind": checkpoint["kind"],
        "angle_deg": _json_float(checkpoint["angle_deg"]),
        "channels": list(checkpoint["channels"]),
        "targets": list(checkpoint["targets"]),
        "rate_hz": _json_float(checkpoint["rate_hz"]),
        "window": int(checkpoint["config"].get("window", 1)),
        "inputs": spec_of(checkpoint.get("inputs")).model_dump(mode="json"),
        "input": INPUT_NAME,
        "output": OUTPUT_NAME,
        "checkpoint_sha256": checkpoint_sha256(checkpoint),
        "train_data_sha256": checkpoint.get("train_data_sha256"),
        "params": _jsonable(checkpoint.get("params", {}), "the checkpoint's params"),
        "cues": None if cue_pack is None else _jsonable(cue_pack, "the cue pack"),
    }


def input_example(checkpoint: dict[str, Any]) -> np.ndarray:
    """Three plausible inputs: the training mean of the inputs and one std either side (raw volts
    never below 0 V). For ls, whose preprocessing is the identity, that is -1, 0 and 1 on every channel."""
    pre = checkpoint["preprocessing"]
    mean, std = pre["x_mean"].double().numpy(), pre["x_std"].double().numpy()
    rows = mean[None, :] + np.array([-1.0, 0.0, 1.0])[:, None] * std[None, :]
    if spec_of(checkpoint.get("inputs")).kind == "volts":
        rows = np.clip(rows, 0.0, None)
    window = int(checkpoint["config"].get("window", 1))
    if checkpoint["kind"] == "lstm":
        rows = np.repeat(rows[:, None, :], window, axis=1)  # a steady reading over the whole window
    return rows.astype(np.float32)


def verify_onnx(checkpoint: dict[str, Any], model: bytes, example: np.ndarray) -> None:
    """Run the graph on `example` with onnxruntime, as the client will, and check that it gives the
    checkpoint's own newtons (the Predictor's, within float32 rounding); ValueError if not."""
    import onnxruntime as ort

    from pipeline.modelling.predict import Predictor

    session = ort.InferenceSession(model, providers=["CPUExecutionProvider"])
    got = session.run(None, {INPUT_NAME: example})[0]
    n_in = example.shape[-1]
    # the LSTM's example rows are windows: predict each as a trial of its own, keep its last sample
    x = example.reshape(-1, n_in).astype(np.float64)
    trials = np.repeat(np.arange(len(example)), x.shape[0] // len(example))
    expected = Predictor(checkpoint).predict_inputs(x, trials)
    expected = expected.reshape(len(example), -1, expected.shape[-1])[:, -1]
    tolerance = 1e-5 * max(float(np.abs(expected).max()), 1.0)
    if got.shape != expected.shape or not np.allclose(got, expected, rtol=0, atol=tolerance):
        raise ValueError(
            f"the exported {checkpoint['kind']} graph does not compute what its checkpoint does: "
            f"{got.tolist()} against {expected.tolist()} N on the input example"
        )


def log_onnx_model(
    checkpoint: dict[str, Any], cue_pack: dict[str, Any] | None, *, name: str = "model"
) -> ModelInfo:
    """Log the checkpoint's ONNX graph as an MLflow model in the active run; returns its ModelInfo
    (`.model_uri` is what `mlflow.register_model` takes)."""
    import mlflow
    import onnx
    from mlflow.models import ModelSignature
    from mlflow.types.schema import Schema, TensorSpec

    if mlflow.active_run() is None:
        raise RuntimeError(f"log_onnx_model({name!r}) needs an active MLflow run (mlflow.start_run())")
    meta = deploy_metadata(checkpoint, cue_pack)
    model = to_onnx(checkpoint, description_sha256(meta))
    meta["onnx_sha256"] = hashlib.sha256(model).hexdigest()  # the bytes MLflow writes (a test checks)
    example = input_example(checkpoint)
    verify_onnx(checkpoint, model, example)  # MLflow's own check below only sees that it runs
    proto = onnx.load_from_string(model)
    n_out = len(checkpoint["targets"])
    signature = ModelSignature(
        inputs=Schema([TensorSpec(np.dtype(np.float32), (-1, *example.shape[1:]), INPUT_NAME)]),
        outputs=Schema([TensorSpec(np.dtype(np.float32), (-1, n_out), OUTPUT_NAME)]),
    )
    return mlflow.onnx.log_model(
        onnx_model=proto,
        name=name,
        signature=signature,
        input_example={INPUT_NAME: example},
        metadata={"needlecue": meta},
        pip_requirements=["onnxruntime"],
        # MLflow's default lists CUDA first, then warns on every CPU-only load that it is missing
        onnx_execution_providers=["CPUExecutionProvider"],
        # one self-contained model.onnx (the default splits tensors > 1 kB into side files)
        save_as_external_data=False,
    )
