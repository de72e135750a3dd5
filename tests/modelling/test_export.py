"""Deployable models: the ONNX graph computes what the Predictor computes, byte-stable, logged to MLflow
with a signature, an input example, the needlecue metadata block and no pickles."""

from __future__ import annotations

import hashlib
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from pipeline.config import FNNParams, LSParams, LSTMParams
from pipeline.modelling import export
from pipeline.modelling.checkpoint import load_checkpoint, save_checkpoint
from pipeline.modelling.fit import fit
from pipeline.modelling.inputs import sequence_order, window_index
from pipeline.modelling.predict import Predictor
from pipeline.vocab import description_sha256
from tests.modelling.frames import make_frame

CHANNELS = ["fsr1", "fsr2", "fsr3"]
TINY = {
    "ls": LSParams(),
    "fnn": FNNParams(hidden=(8, 8), max_epochs=6, patience=3, batch_size=64),
    "lstm": LSTMParams(window=6, hidden=6, max_epochs=3, patience=2, batch_size=64),
}


@pytest.fixture(scope="module")
def checkpoints() -> dict[str, dict]:
    """One tiny trained checkpoint per kind (a few hundred synthetic rows)."""
    train, val = make_frame(4, seed=0), make_frame(1, seed=1, batch_id="b2")
    return {kind: fit(kind, params, train, val).checkpoint for kind, params in TINY.items()}


def onnx_inputs(checkpoint: dict, frame: pd.DataFrame) -> np.ndarray:
    """The graph's input for every row of a frame: its volts, or for the LSTM its window of raw volts
    built within its trial exactly as training does (first sample repeated)."""
    volts = frame[checkpoint["channels"]].to_numpy(np.float64)
    if checkpoint["kind"] != "lstm":
        return volts.astype(np.float32)
    codes = frame.groupby(["batch_id", "trial_id"], sort=False).ngroup().to_numpy(np.int64)
    order, start = sequence_order(codes, frame["t_s"].to_numpy(np.float64))
    windows = np.empty((len(frame), checkpoint["config"]["window"], volts.shape[1]))
    windows[order] = volts[order][window_index(start, checkpoint["config"]["window"])]
    return windows.astype(np.float32)


def run_onnx(model: bytes, x: np.ndarray) -> np.ndarray:
    import onnxruntime as ort

    session = ort.InferenceSession(model, providers=["CPUExecutionProvider"])
    return session.run(None, {export.INPUT_NAME: x})[0]


@pytest.mark.parametrize("kind", ["ls", "fnn", "lstm"])
def test_onnx_graph_computes_what_the_predictor_computes(kind: str, checkpoints) -> None:
    # given: a trained checkpoint and two unseen trials
    checkpoint = checkpoints[kind]
    frame = make_frame(2, seed=7, batch_id="b9")
    expected = Predictor(checkpoint).predict(frame)
    # when: the graph runs on raw volts, all rows at once and one row at a time
    model = export.to_onnx(checkpoint)
    x = onnx_inputs(checkpoint, frame)
    batch = run_onnx(model, x)
    single = np.concatenate([run_onnx(model, x[i : i + 1]) for i in range(0, len(x), 17)])
    # then: newtons equal to the Predictor's within float32 rounding, for any batch size
    assert batch.shape == (len(frame), 3) and batch.dtype == np.float32
    scale = np.abs(expected).max()
    np.testing.assert_allclose(batch, expected, rtol=0, atol=1e-5 * scale)
    np.testing.assert_allclose(single, expected[::17], rtol=0, atol=1e-5 * scale)


def test_onnx_graph_is_self_describing_with_a_dynamic_batch(checkpoints) -> None:
    import onnx

    # given: the LSTM's graph
    proto = onnx.load_from_string(export.to_onnx(checkpoints["lstm"]))
    # when: reading its interface and metadata
    (inp,), (out,) = proto.graph.input, proto.graph.output
    dims = [d.dim_param or d.dim_value for d in inp.type.tensor_type.shape.dim]
    info = json.loads({p.key: p.value for p in proto.metadata_props}["needlecue"])
    # then: volts (batch, window, channels) in, force_n (batch, 3) out, and the graph says what it reads
    assert (inp.name, out.name) == ("inputs", "force_n")
    assert dims == [export.BATCH_DIM, 6, 3]
    assert [d.dim_param or d.dim_value for d in out.type.tensor_type.shape.dim] == [export.BATCH_DIM, 3]
    assert info["channels"] == CHANNELS and info["window"] == 6 and info["kind"] == "lstm"
    assert not any(t.data_location == onnx.TensorProto.EXTERNAL for t in proto.graph.initializer)


def test_onnx_bytes_are_the_same_in_another_process(checkpoints, tmp_path: Path) -> None:
    import torch

    # given: an LSTM checkpoint on disk, exported here
    path = tmp_path / "model.pt"
    save_checkpoint(checkpoints["lstm"], path)
    here = export.to_onnx(load_checkpoint(path))
    # when: exporting it again in this process and in a fresh one
    again = export.to_onnx(checkpoints["lstm"])
    code = (
        "import hashlib, sys; from pipeline.modelling import checkpoint, export; "
        "print(hashlib.sha256(export.to_onnx(checkpoint.load_checkpoint(sys.argv[1]))).hexdigest())"
    )
    other = subprocess.run(
        [sys.executable, "-c", code, str(path)], capture_output=True, text=True, check=True
    )
    # then: identical bytes, and exporting left the caller's RNG alone
    assert again == here
    assert other.stdout.strip() == hashlib.sha256(here).hexdigest()
    state = torch.get_rng_state()
    export.to_onnx(checkpoints["fnn"])
    assert torch.equal(state, torch.get_rng_state())


def test_deploy_metadata_identifies_the_model_and_carries_the_cue_pack(checkpoints) -> None:
    # given: the FNN checkpoint, a retrained identical one and one trained with another seed
    ck = checkpoints["fnn"]
    train, val = make_frame(4, seed=0), make_frame(1, seed=1, batch_id="b2")
    same = fit("fnn", TINY["fnn"], train, val).checkpoint
    other = fit("fnn", TINY["fnn"].model_copy(update={"seed": 1}), train, val).checkpoint
    pack = {"format": "test-pack", "thresholds": [0.1, 0.2]}
    # when: building the metadata block
    meta = export.deploy_metadata(ck, pack)
    # then: plain JSON with everything a client needs, and a hash that follows the weights only
    assert json.loads(json.dumps(meta, allow_nan=False)) == meta
    assert meta["format"] == "needlecue-deploy/3" and meta["kind"] == "fnn"
    assert meta["inputs"] == ck["inputs"]  # how the client computes what the graph reads
    assert (meta["channels"], meta["targets"], meta["window"]) == (CHANNELS, ["fx", "fy", "fz"], 1)
    assert meta["angle_deg"] == 30.0 and meta["rate_hz"] == pytest.approx(30.0)
    assert (meta["input"], meta["output"], meta["cues"]) == ("inputs", "force_n", pack)
    assert meta["train_data_sha256"] == ck["train_data_sha256"] and meta["params"]["hidden"] == [8, 8]
    assert meta["checkpoint_sha256"] == export.deploy_metadata(same, None)["checkpoint_sha256"]
    assert meta["checkpoint_sha256"] != export.deploy_metadata(other, None)["checkpoint_sha256"]


def test_bad_inputs_are_clear_errors(checkpoints) -> None:
    # given: a dict that is no checkpoint, and a cue pack that is not plain data
    # when / then: each is refused, saying what is wrong
    with pytest.raises(ValueError, match="not a needlecue-model/1 checkpoint"):
        export.to_onnx({"format": "something-else"})
    with pytest.raises(ValueError, match="cue pack is not plain JSON"):
        export.deploy_metadata(checkpoints["ls"], {"limit": np.float32(1.0)})
    with pytest.raises(RuntimeError, match="needs an active MLflow run"):
        export.log_onnx_model(checkpoints["ls"], None)


def test_logged_model_has_signature_example_metadata_and_no_pickles(checkpoints, tmp_path: Path) -> None:
    import mlflow
    from mlflow.models import Model

    # given: a run in an experiment whose artifacts live in the test's temp folder
    checkpoint = checkpoints["lstm"]
    experiment = mlflow.create_experiment("export-test", artifact_location=(tmp_path / "artifacts").as_uri())
    # when: logging the LSTM as an ONNX model and downloading it again
    with mlflow.start_run(experiment_id=experiment):
        info = export.log_onnx_model(checkpoint, {"format": "test-pack"}, name="force-model")
    folder = Path(
        mlflow.artifacts.download_artifacts(artifact_uri=info.model_uri, dst_path=str(tmp_path / "dl"))
    )
    model = Model.load(folder / "MLmodel")
    files = sorted(p.name for p in folder.rglob("*") if p.is_file())
    example = json.loads((folder / "input_example.json").read_text())
    # then: a float32 tensor signature with a free batch, a real-looking example, our metadata, the
    # exported graph byte for byte, and nothing that would be unpickled on load
    (inp,), (out,) = model.signature.inputs.inputs, model.signature.outputs.inputs
    assert (inp.name, inp.type, tuple(inp.shape)) == ("inputs", np.dtype(np.float32), (-1, 6, 3))
    assert (out.name, out.type, tuple(out.shape)) == ("force_n", np.dtype(np.float32), (-1, 3))
    x = np.asarray(example["inputs"] if isinstance(example, dict) else example, dtype=np.float32)
    assert x.shape == (3, 6, 3) and np.allclose(x[1, 0], checkpoint["preprocessing"]["x_mean"].numpy())
    meta = model.metadata["needlecue"]
    assert {k: v for k, v in meta.items() if k != "onnx_sha256"} == export.deploy_metadata(
        checkpoint, {"format": "test-pack"}
    )
    # the graph MLflow wrote is the one exported with the description's hash, and the description
    # names it: each vouches for the other (pipeline.client.folder)
    graph = (folder / "model.onnx").read_bytes()
    assert graph == export.to_onnx(checkpoint, description_sha256(meta))
    assert meta["onnx_sha256"] == hashlib.sha256(graph).hexdigest()
    assert "model.onnx" in files and "MLmodel" in files
    assert not [f for f in files if f.endswith((".pkl", ".pickle")) or "python_model" in f], files
    assert np.isfinite(run_onnx((folder / "model.onnx").read_bytes(), x)).all()


def test_a_graph_that_computes_something_else_is_refused_before_logging(checkpoints) -> None:
    # given: the FNN's own graph, and the LS model's graph passed off as the FNN's
    fnn, ls = checkpoints["fnn"], checkpoints["ls"]
    example = export.input_example(fnn)
    # when / then: its own graph passes, the other one is refused, naming the kind
    export.verify_onnx(fnn, export.to_onnx(fnn), example)
    with pytest.raises(ValueError, match="exported fnn graph does not compute what its checkpoint does"):
        export.verify_onnx(fnn, export.to_onnx(ls), example)
