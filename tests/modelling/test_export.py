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

from needlecue_runtime.features import InputTransform, unit_inputs
from needlecue_runtime.frontend import Divider, Transimpedance
from needlecue_runtime.vocab import INPUT_NAMES, description_sha256
from pipeline.config import InputParams
from pipeline.modelling import export
from pipeline.modelling.checkpoint import load_checkpoint, save_checkpoint
from pipeline.modelling.fit import fit
from pipeline.modelling.kinds.fnn import FNNParams
from pipeline.modelling.kinds.ls import LSParams
from pipeline.modelling.kinds.lstm import LSTMParams
from pipeline.modelling.predictor import Predictor
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


def graph_inputs(checkpoint: dict, frame: pd.DataFrame, unit: tuple | None = None) -> dict[str, np.ndarray]:
    """The graph's inputs for every row of a frame, in its row order: each row's window of raw volts
    and of rest readings, built within its trial as training does (first sample repeated), the unit
    read through `unit` (`features.unit_inputs`; None: uncalibrated)."""
    unit = unit or unit_inputs(None, None, len(checkpoint["channels"]))
    parts, rows = [], []
    for _, trial in frame.groupby(["batch_id", "trial_id"], sort=False):
        trial = trial.sort_values("t_s")
        volts, t = trial[checkpoint["channels"]].to_numpy(np.float64), trial["t_s"].to_numpy(np.float64)
        parts.append(export.graph_feed(checkpoint, volts, t, np.arange(len(trial)), unit))
        rows.append(trial.index.to_numpy())
    order = np.argsort(np.concatenate(rows))
    return {
        name: np.concatenate([p[name] for p in parts])[order] if name in INPUT_NAMES[:2] else parts[0][name]
        for name in INPUT_NAMES
    }


def run_onnx(model: bytes, feed: dict[str, np.ndarray]) -> np.ndarray:
    import onnxruntime as ort

    session = ort.InferenceSession(model, providers=["CPUExecutionProvider"])
    return session.run(None, feed)[0]


def rows(feed: dict[str, np.ndarray], i: slice) -> dict[str, np.ndarray]:
    return {k: v[i] if k in INPUT_NAMES[:2] else v for k, v in feed.items()}


@pytest.mark.parametrize("kind", ["ls", "fnn", "lstm"])
def test_onnx_graph_computes_what_the_predictor_computes(kind: str, checkpoints) -> None:
    # given: a trained checkpoint and two unseen trials
    checkpoint = checkpoints[kind]
    frame = make_frame(2, seed=7, batch_id="b9")
    expected = Predictor(checkpoint).predict(frame)
    # when: the graph runs on raw volts, all rows at once and one row at a time
    model = export.to_onnx(checkpoint)
    feed = graph_inputs(checkpoint, frame)
    batch = run_onnx(model, feed)
    single = np.concatenate([run_onnx(model, rows(feed, slice(i, i + 1))) for i in range(0, len(frame), 17)])
    # then: newtons equal to the Predictor's within float32 rounding, for any batch size
    assert batch.shape == (len(frame), 3) and batch.dtype == np.float32
    scale = np.abs(expected).max()
    np.testing.assert_allclose(batch, expected, rtol=0, atol=1e-5 * scale)
    np.testing.assert_allclose(single, expected[::17], rtol=0, atol=1e-5 * scale)


CIRCUITS = {
    "supply": Divider(circuit="divider", supply_v=5.0, fixed_kohm=10.0, series_kohm=0.5),
    "ground": Divider(circuit="divider", supply_v=3.3, fixed_kohm=4.7, fsr_at="ground"),
    "transimpedance": Transimpedance(circuit="transimpedance", drive_v=1.0, feedback_kohm=3.0, offset_v=0.1),
}


@pytest.mark.parametrize("inputs", ["volts", "rest_volts", "conductance", "rest_conductance"])
@pytest.mark.parametrize("circuit", sorted(CIRCUITS))
def test_the_graph_reads_a_calibrated_unit_through_its_own_circuit_as_the_predictor_does(
    inputs: str, circuit: str
) -> None:
    # given: a model trained on one circuit's readings, and a unit with another circuit and a
    # calibration of its conductance (the training circuit: a divider at the supply)
    params = LSParams(inputs=InputParams(kind=inputs, rest_s=0.3))
    checkpoint = fit("ls", params, make_frame(4, seed=0), front_end=CIRCUITS["supply"]).checkpoint
    fe = CIRCUITS[circuit]
    transform = InputTransform(
        ((1.1, 0.05, 0.0), (0.0, 0.9, 0.1), (0.02, 0.0, 1.0)), (0.5, 0.0, -0.3), "conductance", fe
    )
    frame = make_frame(2, seed=7, batch_id="b9")
    frame[CHANNELS] = frame[CHANNELS] * (0.6 if circuit != "transimpedance" else 1.0) + 0.4
    # when: the graph and the Predictor read it calibrated, and uncalibrated through its circuit
    model = export.to_onnx(checkpoint)
    calibrated = run_onnx(model, graph_inputs(checkpoint, frame, unit_inputs(transform, fe, 3)))
    through = run_onnx(model, graph_inputs(checkpoint, frame, unit_inputs(None, fe, 3)))
    predictor = Predictor(checkpoint)
    expected, expected_through = predictor.predict(frame, transform, fe), predictor.predict(frame, None, fe)
    # then: the same newtons, and the calibration made a difference
    scale = np.abs(expected).max()
    np.testing.assert_allclose(calibrated, expected, rtol=0, atol=1e-5 * scale)
    np.testing.assert_allclose(through, expected_through, rtol=0, atol=1e-5 * scale)
    assert not np.allclose(expected, expected_through, rtol=0, atol=1e-3 * scale)


def test_an_inputs_domain_calibration_is_applied_to_the_inputs() -> None:
    # given: a model on rest-relative volts with no circuit, and a unit calibrated on its inputs
    checkpoint = fit("ls", LSParams(inputs=InputParams(kind="rest_volts")), make_frame(4, seed=0)).checkpoint
    transform = InputTransform(((1.2, 0.0, 0.1), (0.0, 0.8, 0.0), (0.0, 0.1, 1.0)), (0.01, -0.02, 0.0))
    frame = make_frame(2, seed=7, batch_id="b9")
    # when / then: the graph gives the Predictor's newtons for the calibrated unit
    got = run_onnx(
        export.to_onnx(checkpoint), graph_inputs(checkpoint, frame, unit_inputs(transform, None, 3))
    )
    expected = Predictor(checkpoint).predict(frame, transform)
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-5 * np.abs(expected).max())


def test_onnx_graph_is_self_describing_with_a_dynamic_batch(checkpoints) -> None:
    import onnx

    # given: the LSTM's graph and the FNN's (which reads no window)
    proto = onnx.load_from_string(export.to_onnx(checkpoints["lstm"]))
    fnn = onnx.load_from_string(export.to_onnx(checkpoints["fnn"]))
    # when: reading their interface and metadata
    dims = {
        i.name: [d.dim_param or d.dim_value for d in i.type.tensor_type.shape.dim] for i in proto.graph.input
    }
    (out,) = proto.graph.output
    info = json.loads({p.key: p.value for p in proto.metadata_props}["needlecue"])
    # then: raw volts and rest readings (batch, window, channels) and the unit in, force_n out, the
    # same five inputs for every kind, and the graph says what it reads
    assert list(dims) == list(INPUT_NAMES) == [i.name for i in fnn.graph.input]
    assert dims["reading"] == dims["rest_reading"] == [export.BATCH_DIM, 6, 3]
    assert dims["volts_per_count"] == [1]
    assert (dims["unit_matrix"], dims["unit_offset"], dims["unit_circuit"]) == ([3, 3], [3], [6])
    assert out.name == "force_n"
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
    assert meta["format"] == "needlecue-deploy/4" and meta["kind"] == "fnn"
    assert meta["inputs"] == ck["inputs"]  # how the client computes what the graph reads
    assert (meta["channels"], meta["targets"], meta["window"]) == (CHANNELS, ["fx", "fy", "fz"], 1)
    assert meta["angle_deg"] == 30.0 and meta["rate_hz"] == pytest.approx(30.0)
    assert (meta["graph_inputs"], meta["output"], meta["cues"]) == (list(INPUT_NAMES), "force_n", pack)
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
        trial = make_frame(1, seed=3)
        recording = (trial[CHANNELS].to_numpy(), trial["t_s"].to_numpy())
        info = export.log_onnx_model(checkpoint, {"format": "test-pack"}, name="force-model", trial=recording)
    folder = Path(
        mlflow.artifacts.download_artifacts(artifact_uri=info.model_uri, dst_path=str(tmp_path / "dl"))
    )
    model = Model.load(folder / "MLmodel")
    files = sorted(p.name for p in folder.rglob("*") if p.is_file())
    example = json.loads((folder / "input_example.json").read_text())
    # then: a float64 tensor signature naming the five inputs with a free batch, a real raw example,
    # our metadata, the exported graph byte for byte, and nothing that would be unpickled on load
    specs = {i.name: (i.type, tuple(i.shape)) for i in model.signature.inputs.inputs}
    f64 = np.dtype(np.float64)
    assert specs == {
        "reading": (f64, (-1, 6, 3)),
        "rest_reading": (f64, (-1, 6, 3)),
        "volts_per_count": (f64, (1,)),
        "unit_matrix": (f64, (3, 3)),
        "unit_offset": (f64, (3,)),
        "unit_circuit": (f64, (6,)),
    }
    (out,) = model.signature.outputs.inputs
    assert (out.name, out.type, tuple(out.shape)) == ("force_n", np.dtype(np.float32), (-1, 3))
    x = {k: np.asarray(v, dtype=np.float64) for k, v in example.items()}
    trial = make_frame(1, seed=3)
    raw = trial[CHANNELS].to_numpy()
    assert x["reading"].shape == (3, 6, 3) and np.array_equal(
        x["reading"][2, -1], raw[-1]
    )  # the real last sample
    assert np.array_equal(x["unit_matrix"], np.eye(3)) and not x["unit_circuit"].any()
    meta = model.metadata["needlecue"]
    assert {k: v for k, v in meta.items() if k != "onnx_sha256"} == export.deploy_metadata(
        checkpoint, {"format": "test-pack"}
    )
    # the graph MLflow wrote is the one exported with the description's hash, and the description
    # names it: each vouches for the other (needlecue_client.folder)
    graph = (folder / "model.onnx").read_bytes()
    assert graph == export.to_onnx(checkpoint, description_sha256(meta))
    assert meta["onnx_sha256"] == hashlib.sha256(graph).hexdigest()
    assert "model.onnx" in files and "MLmodel" in files
    assert not [f for f in files if f.endswith((".pkl", ".pickle")) or "python_model" in f], files
    assert np.isfinite(run_onnx((folder / "model.onnx").read_bytes(), x)).all()
    assert "Takes the estimator's raw readings `reading` float64 (batch, 6, 3)" in export.describe(checkpoint)


def test_mlflow_reads_mlmodel_files_through_libyaml_while_a_model_is_logged(
    checkpoints, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import mlflow
    import yaml
    from mlflow.models import Model
    from mlflow.models import model as mlflow_model

    # given: a logged model with a cue pack of the size the pipeline's are (thousands of numbers),
    # and libyaml's loader counting the documents it reads
    class Counting(yaml.CSafeLoader):
        documents = 0

        def __init__(self, stream: object) -> None:
            type(self).documents += 1
            super().__init__(stream)

    class CountingDumper(yaml.CSafeDumper):
        documents = 0

        def __init__(self, stream: object, **kwargs: object) -> None:
            type(self).documents += 1
            super().__init__(stream, **kwargs)

    monkeypatch.setattr(yaml, "CSafeLoader", Counting)
    monkeypatch.setattr(yaml, "CSafeDumper", CountingDumper)
    pack = {"format": "test-pack", "templates": [[i / 7, i / 11, i / 13] for i in range(4000)]}
    experiment = mlflow.create_experiment("yaml-test", artifact_location=(tmp_path / "artifacts").as_uri())
    # when: logging it (MLflow loads what it logged to check the input example)
    with mlflow.start_run(experiment_id=experiment):
        trial = make_frame(1, seed=3)
        recording = (trial[CHANNELS].to_numpy(), trial["t_s"].to_numpy())
        info = export.log_onnx_model(checkpoints["ls"], pack, trial=recording)
    # then: MLflow's own loads went through libyaml, and MLflow's module is as it was afterwards
    assert Counting.documents, "Model.load no longer reads through mlflow.models.model.yaml: no speed-up"
    assert CountingDumper.documents, "Model.save no longer writes through mlflow.models.model.yaml"
    assert mlflow_model.yaml is yaml
    # and libyaml gives the same model as pure-Python PyYAML
    dst = str(tmp_path / "dl")
    folder = Path(mlflow.artifacts.download_artifacts(artifact_uri=info.model_uri, dst_path=dst))
    with export.libyaml_mlmodels():
        fast = Model.load(folder / "MLmodel").to_dict()
    assert fast == Model.load(folder / "MLmodel").to_dict()
    assert fast["metadata"]["needlecue"]["cues"] == pack
    # and the MLmodel written is the text pure-Python PyYAML writes
    text = (folder / "MLmodel").read_text()
    assert text == yaml.dump(yaml.safe_load(text), Dumper=yaml.SafeDumper, default_flow_style=False)
    # and blocks inside blocks (or on other threads) keep it until the last one ends
    with export.libyaml_mlmodels():
        with export.libyaml_mlmodels():
            pass
        counted = Counting.documents
        Model.load(folder / "MLmodel")
        assert Counting.documents == counted + 1
    assert mlflow_model.yaml is yaml


def test_a_graph_that_computes_something_else_is_refused_before_logging(checkpoints) -> None:
    # given: the FNN's own graph, and the LS model's graph passed off as the FNN's
    fnn, ls = checkpoints["fnn"], checkpoints["ls"]
    example = export.input_example(fnn)
    # when / then: its own graph passes, the other one is refused, naming the kind
    export.verify_onnx(fnn, export.to_onnx(fnn), example)
    with pytest.raises(ValueError, match="exported fnn graph does not compute what its checkpoint does"):
        export.verify_onnx(fnn, export.to_onnx(ls), example)


def test_an_lstm_of_one_sample_exports_as_a_sequence_of_one() -> None:
    # given: an LSTM whose window is its current sample only
    params = LSTMParams(window=1, hidden=4, max_epochs=2, patience=1, batch_size=64)
    checkpoint = fit("lstm", params, make_frame(4, seed=0)).checkpoint
    frame = make_frame(1, seed=7, batch_id="b9")
    # when / then: its graph reads (batch, 1, channels) and gives the Predictor's newtons
    got = run_onnx(export.to_onnx(checkpoint), graph_inputs(checkpoint, frame))
    expected = Predictor(checkpoint).predict(frame)
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-5 * np.abs(expected).max())
