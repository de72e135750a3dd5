"""Deployable force models: a needlecue checkpoint as a self-contained ONNX graph, logged to MLflow.

The graph reads what the estimator sends and returns newtons. It computes the model's inputs from the
raw volts (`pipeline.modelling.front`), reads the unit through its calibration, given as data, and
holds the checkpoint's standardisation, so that `mlflow models serve`, MLflow's pyfunc and a simulator
in any language need no needlecue code, and the Python client no pickle (docs/deploy.md):

    inputs  `reading`         float64 (N, window, C)  raw readings, oldest first, in `channels` order
            `rest_reading`    float64 (N, window, C)  the rest reading in effect at each of those samples
            `volts_per_count` float64 (1,)            1 for volts; vref / (2^bits - 1) for ADC counts
            `unit_matrix`     float64 (C, C)          the unit's calibration (identity: uncalibrated)
            `unit_offset`     float64 (C,)
            `unit_circuit`    float64 (6,)            the unit's circuit (zeros: the model's own)
    output  `force_n`         float32 (N, T)          the model's `targets` in N, one column each

`targets` are the axes the reference sensor recorded and the model was trained on: a non-empty subset
of fx, fy, fz in that order (all three, or only fz from a load cell, say), never padded to three.
`window` is 1 for ls and fnn. The same checkpoint gives the same ONNX bytes, in any process (a test
checks it), and the MLflow model carries a `needlecue` metadata block (`deploy_metadata`) with what a
client needs besides: the rest period, the channels and rate, the cue pack. What a simulator runs is
verified as one (`needlecue_client.folder`): the graph's own metadata holds the sha256 of that block,
and the block the sha256 of the graph (`onnx_sha256`), both recorded when the model is logged.

torch, onnx and mlflow are imported inside the functions, so importing this module is cheap.
"""

from __future__ import annotations

import hashlib
import io
import json
import math
import threading
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING, Any

import numpy as np

from needlecue_runtime.features import features_at, rest_reading, spec_of, unit_inputs
from needlecue_runtime.vocab import (
    AXES,
    DEPLOY_FORMAT,
    INPUT_NAMES,
    OUTPUT_NAME,
    axes_in_order,
    description_sha256,
)
from pipeline.modelling.checkpoint import ModelConfig, check_checkpoint, checkpoint_sha256
from pipeline.modelling.front import front_module
from pipeline.modelling.inputs import window_index
from pipeline.modelling.kinds import kind_of

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
    """The checkpoint's model as one module, the graph's inputs (`INPUT_NAMES`) in, newtons out (eval
    mode): the front (float64) computes the model's inputs, the model's kind gives the rest (float32)."""
    from torch import nn

    check_checkpoint(checkpoint, "export")
    kind = kind_of(checkpoint["kind"], "export")
    cfg = ModelConfig.from_dict(checkpoint["config"])
    network = kind.load(cfg, checkpoint["state_dict"], checkpoint["preprocessing"]).graph()
    front = front_module(spec_of(checkpoint.get("inputs")), sequence=kind.sequence)

    class Graph(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.front, self.network = front, network

        def forward(self, *graph_inputs: torch.Tensor) -> torch.Tensor:
            return self.network(self.front(*graph_inputs).float())

    return Graph().eval()


def graph_window(checkpoint: dict[str, Any]) -> int:
    """Samples per row of the graph's `reading` (a sequence kind's window, else 1)."""
    return kind_of(checkpoint["kind"], "export").window(ModelConfig.from_dict(checkpoint["config"]))


def to_onnx(checkpoint: dict[str, Any], description: str | None = None) -> bytes:
    """The serialized ONNX model of a checkpoint (see the module docstring for its input and output);
    `description`: the sha256 of the description it is logged with (`description_sha256`)."""
    import onnx
    import torch

    module = deployable_module(checkpoint)
    n_in, window = len(checkpoint["channels"]), graph_window(checkpoint)
    # a batch of 2 in the trace: no dimension of size 1 the exporter might specialise on
    dummy = tuple(torch.from_numpy(a) for a in _steady(2, window, n_in, 2.5))
    buffer = io.BytesIO()
    with warnings.catch_warnings(), torch.no_grad():
        for message in _EXPORTER_NOISE:
            warnings.filterwarnings("ignore", message=message)
        # nn.LSTM's own shape checks turn tensors into Python bools while tracing: harmless here
        warnings.filterwarnings("ignore", category=torch.jit.TracerWarning)
        torch.onnx.export(
            module,
            dummy,
            buffer,
            dynamo=False,
            opset_version=OPSET,
            input_names=list(INPUT_NAMES),
            output_names=[OUTPUT_NAME],
            dynamic_axes={name: {0: BATCH_DIM} for name in (*INPUT_NAMES[:2], OUTPUT_NAME)},
            do_constant_folding=True,
        )
    proto = onnx.load_from_string(buffer.getvalue())
    _keep_every_input(proto, dummy)
    _check_output(proto, checkpoint)
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


def _keep_every_input(proto: Any, dummy: tuple[Any, ...]) -> None:
    """Put back, in order, the inputs the exporter dropped because this model does not read them
    (`rest_reading` for absolute inputs): every graph takes the same six, whatever its kind."""
    import onnx

    found = {i.name: i for i in proto.graph.input}
    inputs = []
    for name, tensor in zip(INPUT_NAMES, dummy, strict=True):
        if name in found:
            inputs.append(found[name])
            continue
        shape = [BATCH_DIM if k == 0 and name in INPUT_NAMES[:2] else d for k, d in enumerate(tensor.shape)]
        inputs.append(onnx.helper.make_tensor_value_info(name, onnx.TensorProto.DOUBLE, shape))
    del proto.graph.input[:]
    proto.graph.input.extend(inputs)


def _check_output(proto: Any, checkpoint: dict[str, Any]) -> None:
    """ValueError unless the graph's output has one column per target: a network with another number
    of outputs than its checkpoint's `targets` would give forces named for the wrong axes."""
    dims = proto.graph.output[0].type.tensor_type.shape.dim
    columns = dims[-1].dim_value if len(dims) == 2 and dims[-1].HasField("dim_value") else None
    if columns != len(checkpoint["targets"]):
        raise ValueError(
            f"the exported {checkpoint['kind']} graph gives {columns} force column(s), its checkpoint's "
            f"targets are {list(checkpoint['targets'])}"
        )


def targets_of(checkpoint: dict[str, Any]) -> list[str]:
    """The checkpoint's `targets`, checked: a non-empty subset of fx, fy, fz in that order (ValueError)."""
    targets = checkpoint.get("targets")
    if not axes_in_order(targets):
        raise ValueError(
            f"the checkpoint's targets are {targets!r}: expected a non-empty list of force axes among "
            f"{', '.join(AXES)}, in that order (the axes its reference recorded)"
        )
    return list(targets)


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
        "targets": targets_of(checkpoint),
        "rate_hz": _json_float(checkpoint["rate_hz"]),
        "window": graph_window(checkpoint),
        "inputs": spec_of(checkpoint.get("inputs")).model_dump(mode="json"),
        "graph_inputs": list(INPUT_NAMES),
        "output": OUTPUT_NAME,
        "checkpoint_sha256": checkpoint_sha256(checkpoint),
        "train_data_sha256": checkpoint.get("train_data_sha256"),
        "params": _jsonable(checkpoint.get("params", {}), "the checkpoint's params"),
        "cues": None if cue_pack is None else _jsonable(cue_pack, "the cue pack"),
    }


VOLTS = np.ones(1)  # `volts_per_count` of readings in volts


def _steady(n: int, window: int, n_in: int, volts: float) -> tuple[np.ndarray, ...]:
    """Graph inputs of `n` rows of a steady reading at `volts`, uncalibrated."""
    v = np.full((n, window, n_in), volts, dtype=np.float64)
    return (v, v.copy(), VOLTS, *unit_inputs(None, None, n_in))


def raw_windows(checkpoint: dict[str, Any], volts: np.ndarray, rows: Any) -> np.ndarray:
    """(len(rows), window, C) windows of one trial's raw `volts` (n, C), each ending at one of `rows`;
    the first sample repeated before the trial's start, as training pads them (`window_index`)."""
    one_trial = np.zeros(len(volts), dtype=np.int64)  # every row's trial starts at row 0
    idx = window_index(one_trial, graph_window(checkpoint))[np.asarray(rows)]
    return np.asarray(volts, dtype=np.float64)[idx]


def graph_feed(
    checkpoint: dict[str, Any], volts: np.ndarray, t: np.ndarray, rows: Any, unit: tuple[np.ndarray, ...]
) -> dict[str, np.ndarray]:
    """The graph's inputs for rows `rows` of one trial (raw `volts` (n, C) at times `t`), its unit read
    through `unit` (`features.unit_inputs`): what a simulator sends, computed from a recording."""
    one_trial = np.zeros(len(volts), dtype=np.int64)
    rest = rest_reading(volts, one_trial, t, spec_of(checkpoint.get("inputs")).rest_s)
    arrays = (raw_windows(checkpoint, volts, rows), raw_windows(checkpoint, rest, rows), VOLTS, *unit)
    return dict(zip(INPUT_NAMES, arrays, strict=True))


def input_example(
    checkpoint: dict[str, Any], trial: tuple[np.ndarray, np.ndarray] | None = None
) -> dict[str, np.ndarray]:
    """The graph's inputs for three rows of a real trial (raw volts (n, C) and times (n,)): its first
    sample, its half-way sample and its last, uncalibrated. Without a trial, a steady 2.5 V reading."""
    n_in = len(checkpoint["channels"])
    if trial is None or len(trial[0]) == 0:
        return dict(zip(INPUT_NAMES, _steady(3, graph_window(checkpoint), n_in, 2.5), strict=True))
    volts, t = trial
    rows = [0, len(volts) // 2, len(volts) - 1]
    return graph_feed(checkpoint, volts, t, rows, unit_inputs(None, None, n_in))


def verify_onnx(checkpoint: dict[str, Any], model: bytes, example: dict[str, np.ndarray]) -> None:
    """Run the graph on `example` with onnxruntime, as a simulator will, and check that it gives the
    checkpoint's own newtons (the Predictor's on the same raw volts, within float32 rounding); ValueError
    if not."""
    import onnxruntime as ort

    from pipeline.modelling.predictor import Predictor

    session = ort.InferenceSession(model, providers=["CPUExecutionProvider"])
    got = session.run(None, example)[0]
    predictor = Predictor(checkpoint)
    expected = []
    scale = float(example[INPUT_NAMES[2]][0])
    for reading, resting in zip(example[INPUT_NAMES[0]], example[INPUT_NAMES[1]], strict=True):
        volts, rest = reading * scale, resting * scale
        # each row as a trial of its own, its window's samples with their own rest readings: the inputs
        # are the features of the volts less those of the rest, row by row, as `features` computes them
        x = features_at(volts, rest, predictor.inputs)
        expected.append(predictor.predict_inputs(x, np.zeros(len(x), dtype=np.int64))[-1])
    expected = np.asarray(expected)
    tolerance = 1e-5 * max(float(np.abs(expected).max()), 1.0)
    if got.shape != expected.shape or not np.allclose(got, expected, rtol=0, atol=tolerance):
        raise ValueError(
            f"the exported {checkpoint['kind']} graph does not compute what its checkpoint does: "
            f"{got.tolist()} against {expected.tolist()} N on the input example"
        )


SIGNATURE_DOC = {
    "reading": "raw estimator readings, counts or V, (batch, window, channels), oldest sample first",
    "rest_reading": (
        "the rest reading in effect at each sample, same unit and shape: the running mean of the "
        "insertion's readings over its first rest_s seconds"
    ),
    "volts_per_count": "(1,): V per reading unit: 1 for volts, vref_v / (2^adc_bits - 1) for counts",
    "unit_matrix": "the unit's calibration matrix (channels, channels); identity: uncalibrated",
    "unit_offset": "the unit's calibration offset (channels,); zeros: uncalibrated",
    "unit_circuit": (
        "the unit's circuit (6,): [circuit, a, b, series_kohm, offset_v, on_conductance]; "
        "zeros: the model's own"
    ),
}


def describe(checkpoint: dict[str, Any]) -> str:
    """The registered version's description: what the graph takes and returns."""
    n, window = len(checkpoint["channels"]), graph_window(checkpoint)
    rest_s = spec_of(checkpoint.get("inputs")).rest_s
    targets = targets_of(checkpoint)
    return (
        f"{checkpoint['kind']} force model for {checkpoint['angle_deg']:g}° insertions. Takes the "
        f"estimator's raw readings `reading` float64 (batch, {window}, {n}), counts or volts, for "
        f"channels {', '.join(checkpoint['channels'])} at {checkpoint['rate_hz']:g} Hz, oldest sample "
        f"first; `rest_reading`, the same shape, the running mean of the insertion's readings over its "
        f"first {rest_s:g} s in effect at each sample; `volts_per_count` (1,), 1 for volts; and the "
        f"unit's calibration `unit_matrix` ({n}, {n}), `unit_offset` ({n},), `unit_circuit` (6,) "
        f"(identity, zeros and zeros: uncalibrated). Returns `force_n` float32 (batch, {len(targets)}): "
        f"{', '.join(targets)} in N. docs/deploy.md."
    )


def log_onnx_model(
    checkpoint: dict[str, Any],
    cue_pack: dict[str, Any] | None,
    *,
    name: str = "model",
    trial: tuple[np.ndarray, np.ndarray] | None = None,
) -> ModelInfo:
    """Log the checkpoint's ONNX graph as an MLflow model in the active run, its input example three
    rows of `trial` (raw volts, times; see `input_example`); returns its ModelInfo (`.model_uri` is
    what `mlflow.register_model` takes)."""
    import mlflow
    import onnx
    from mlflow.models import ModelSignature
    from mlflow.types.schema import Schema, TensorSpec

    if mlflow.active_run() is None:
        raise RuntimeError(f"log_onnx_model({name!r}) needs an active MLflow run (mlflow.start_run())")
    meta = deploy_metadata(checkpoint, cue_pack)
    model = to_onnx(checkpoint, description_sha256(meta))
    meta["onnx_sha256"] = hashlib.sha256(model).hexdigest()  # the bytes MLflow writes (a test checks)
    example = input_example(checkpoint, trial)
    verify_onnx(checkpoint, model, example)  # MLflow's own check below only sees that it runs
    proto = onnx.load_from_string(model)
    n_out = len(meta["targets"])  # one column per target, named by `targets` in the metadata
    f64 = np.dtype(np.float64)
    shapes = {k: (-1, *v.shape[1:]) if k in INPUT_NAMES[:2] else v.shape for k, v in example.items()}
    signature = ModelSignature(
        inputs=Schema([TensorSpec(f64, shapes[k], k) for k in INPUT_NAMES]),
        outputs=Schema([TensorSpec(np.dtype(np.float32), (-1, n_out), OUTPUT_NAME)]),
    )
    with libyaml_mlmodels():
        return mlflow.onnx.log_model(
            onnx_model=proto,
            name=name,
            signature=signature,
            input_example=example,
            metadata={"needlecue": meta, "inputs_doc": SIGNATURE_DOC},
            pip_requirements=["onnxruntime"],
            # MLflow's default lists CUDA first, then warns on every CPU-only load that it is missing
            onnx_execution_providers=["CPUExecutionProvider"],
            # one self-contained model.onnx (the default splits tensors > 1 kB into side files)
            save_as_external_data=False,
        )


_YAML_LOCK = threading.Lock()
_YAML_USERS = 0  # blocks open in this process


@contextmanager
def libyaml_mlmodels() -> Iterator[None]:
    """While open, MLflow's `Model.load` parses MLmodel files with libyaml (PyYAML's CSafeLoader,
    the same safe constructors: the same mapping) instead of pure-Python PyYAML, and `Model.save`
    writes them with it (CSafeDumper: the same text).

    Why: `Model.log` writes the model's MLmodel and loads it twice, to check its input example, and
    a force model's MLmodel is about 210 kB (the cue pack): 0.2 to 0.3 s a parse in pure Python,
    about 9 s of the register stage's 27 s for 18 models, and 0.07 s a write (0.02 s in libyaml).
    MLflow uses `yaml.safe_load` and `yaml.safe_dump` of its module `mlflow.models.model`; that one
    name is replaced, and restored when the last block ends. Without libyaml, nothing changes."""
    import yaml
    from mlflow.models import model as mlflow_model

    global _YAML_USERS
    loader = getattr(yaml, "CSafeLoader", None)
    with _YAML_LOCK:
        current = getattr(mlflow_model, "yaml", None)
        # ours already there: another block (an outer one, another thread's) put it; counted too
        counted = loader is not None and (current is yaml or isinstance(current, _LibyamlSafe))
        if counted:
            if current is yaml:
                mlflow_model.yaml = _LibyamlSafe(yaml, loader)
            _YAML_USERS += 1
    if not counted:  # no libyaml, or MLflow reads its MLmodel otherwise now: its own way
        yield
        return
    try:
        yield
    finally:
        with _YAML_LOCK:
            _YAML_USERS -= 1
            if _YAML_USERS == 0:
                mlflow_model.yaml = yaml


class _LibyamlSafe:
    """PyYAML as `mlflow.models.model` uses it, but for `safe_load` and `safe_dump` through libyaml
    (the same safe representers and the same text: a test compares them)."""

    def __init__(self, yaml: Any, loader: Any) -> None:
        self._yaml, self._loader = yaml, loader

    def safe_load(self, stream: Any) -> Any:
        return self._yaml.load(stream, Loader=self._loader)

    def safe_dump(self, data: Any, stream: Any = None, **kwds: Any) -> Any:
        return self._yaml.dump_all([data], stream, Dumper=self._yaml.CSafeDumper, **kwds)

    def __getattr__(self, name: str) -> Any:  # the rest: PyYAML's own
        return getattr(self._yaml, name)
