"""What the client's tests build: synthetic processed trials, tiny models, registered versions, and
estimator units' calibration documents."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from needlecue_runtime.registry import mlflow_env, store
from needlecue_runtime.unit_calibration import FORMAT as UNIT_FORMAT
from needlecue_runtime.unit_calibration import parse_unit
from needlecue_runtime.vocab import AXES, angle_name
from pipeline.config import InputParams
from pipeline.modelling import export
from pipeline.modelling.checkpoint import CHECKPOINT_FILE, checkpoint_sha256, save_checkpoint
from pipeline.modelling.kinds.fnn import FNNParams
from pipeline.modelling.kinds.ls import LSParams
from pipeline.modelling.kinds.lstm import LSTMParams
from pipeline.modelling.predictor import Predictor
from pipeline.registry import calibrations

UNREACHABLE = "http://127.0.0.1:9"  # the discard port: connection refused at once
CHANNELS = ["fsr1", "fsr2", "fsr3"]
VOLTS = InputParams(kind="volts")  # the client's tests read raw volts (the inputs are tests/modelling's)
TINY = {
    "ls": LSParams(inputs=VOLTS),
    "fnn": FNNParams(hidden=(8, 8), max_epochs=6, patience=3, batch_size=64, inputs=VOLTS),
    "lstm": LSTMParams(window=6, hidden=6, max_epochs=3, patience=2, batch_size=64, inputs=VOLTS),
}


@dataclass(frozen=True)
class Registered:
    uri: str  # the client tests' own MLflow store
    checkpoint: dict  # the LSTM registered there as needle-force-30@champion, version 1, with a cue pack
    pack: dict  # that cue pack


BENCH_UNIT = "est-bench"  # the estimator unit that records `cue_trials`


def cue_evidence(pack: dict, unit: str = BENCH_UNIT) -> dict:
    """A unit calibration's `cues` section whose calibration insertions read as `unit`'s training
    trials in `pack` (a new unit that sits where the training unit does)."""
    est = pack["angle_estimator"]
    return {"levels": est["levels"], "evidence": est["units"][unit]}


class Clock:
    """The client's poll clock (`follow._monotonic`), moved by hand instead of sleeping."""

    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now

    def advance(self, seconds: float) -> None:
        self.now += seconds


def cue_trials(
    angle: float, n_trials: int = 2, batch: str = "b1", seed: int = 0, n: int = 90
) -> pd.DataFrame:
    """Processed-split rows at one insertion angle: 1 s at rest, then loading. The rest reading and the
    direction the volts move in both depend on the angle, as on the real estimator, so the cue tracker's
    angle estimate can tell the angles apart."""
    rng = np.random.default_rng(seed + int(angle))
    direction = np.array([1.0 + angle / 30, 1.0, 1.0 - angle / 60])
    rest = 0.3 + 0.004 * angle * np.array([1.0, -0.5, 0.2])
    t = np.arange(n) / 30.0
    load = np.clip(t - 1.0, 0, None) ** 1.5
    parts = []
    for k in range(n_trials):
        v = rest * np.exp(0.3 * load[:, None] * direction) + 0.001 * rng.normal(size=(n, 3))
        a = np.radians(angle)
        parts.append(
            pd.DataFrame(
                {
                    "batch_id": batch,
                    "trial_id": f"t{k:02d}",
                    "angle_deg": float(angle),
                    "tissue_point": "p1",
                    "unit_id": BENCH_UNIT,
                    "t_s": t,
                    "phase": np.where(t < 1.0, "rest", "insertion"),
                    **{c: v[:, i] for i, c in enumerate(CHANNELS)},
                    "fx": 0.2 * load * np.sin(a) + 0.05 * v[:, 0],
                    "fy": 0.1 * load,
                    "fz": -0.5 * load * np.cos(a),
                }
            )
        )
    return pd.concat(parts, ignore_index=True)


# the output layer of each kind: the rows a model of fewer axes keeps (`keep_axes`)
OUTPUT_LAYER = {
    "ls": ("weight", "bias"),
    "fnn": ("out.weight", "out.bias"),
    "lstm": ("head.weight", "head.bias"),
}


def keep_axes(checkpoint: dict, axes: tuple[str, ...] = ("fz",)) -> dict:
    """`checkpoint` as the model of `axes` alone (a non-empty subset of its targets, in their order): what
    training gives when the reference recorded only those axes (a load cell's fz, say), with this
    model's very numbers for them, so its force is exactly the given model's on those axes."""
    import copy

    keep = [list(checkpoint["targets"]).index(a) for a in axes]
    out = copy.deepcopy(checkpoint)
    for key in OUTPUT_LAYER[checkpoint["kind"]]:
        out["state_dict"][key] = out["state_dict"][key][keep].clone()
    for key in ("y_mean", "y_std"):
        out["preprocessing"][key] = out["preprocessing"][key][keep].clone()
    out["config"] = {**out["config"], "n_out": len(axes)}
    out["targets"] = list(axes)
    return out


def cue_predictions(checkpoint: dict, train_by_angle: Mapping[float, pd.DataFrame]) -> dict[str, dict]:
    """`build_cue_pack`'s `predicted`: {kind: {angle: forces}}, the model on every angle's training frame
    (its volts only, as a deployed model sees them)."""
    predictor = Predictor(checkpoint)
    return {
        predictor.kind: {
            a: predictor.predict(frame.drop(columns=list(AXES))) for a, frame in train_by_angle.items()
        }
    }


def register(
    uri: str,
    root: Path,
    checkpoint: dict,
    pack: dict | None = None,
    angle: float = 30.0,
    with_checkpoint: bool = False,
) -> str:
    """Log `checkpoint` as ONNX in store `uri` (artifacts under `root`), register it, make it champion.
    `with_checkpoint`: the run also logs `checkpoint/model.pt`, as the register stage's runs do."""
    import mlflow

    client = store.connect(uri)
    name = store.model_name(angle)
    with mlflow_env.fluent(client.tracking_uri):
        exp = mlflow.get_experiment_by_name(store.EXPERIMENT)
        exp_id = (
            exp.experiment_id
            if exp
            else mlflow.create_experiment(store.EXPERIMENT, artifact_location=(root / "artifacts").as_uri())
        )
        with mlflow.start_run(experiment_id=exp_id):
            info = export.log_onnx_model(checkpoint, pack)
            if with_checkpoint:
                path = root / "checkpoints" / checkpoint_sha256(checkpoint) / CHECKPOINT_FILE
                save_checkpoint(checkpoint, path)
                mlflow.log_artifact(str(path), artifact_path="checkpoint")
        version = mlflow.register_model(info.model_uri, name).version
    client.set_registered_model_alias(name, store.CHAMPION, version)
    return str(version)


def unit_document(
    unit_id: str,
    models: Mapping[float, dict],
    matrix: list[list[float]] | None = None,
    offset: list[float] | None = None,
    cues: dict | None = None,
) -> dict:
    """A needlecue-unit/4 document of `unit_id` whose transform (one per kind of `models`, {angle:
    checkpoint}) was "made with" those checkpoints; the identity unless `matrix` / `offset` are given;
    `cues`: what its calibration insertions tell the angle estimator (`cue_evidence`; None: nothing)."""
    transforms: dict[str, dict] = {}
    for angle, checkpoint in models.items():
        n = len(checkpoint["channels"])
        t = transforms.setdefault(
            checkpoint["kind"],
            {
                "matrix": matrix or np.eye(n).tolist(),
                "offset": offset or [0.0] * n,
                "domain": "inputs",
                "fitted_through": [],
                "models": {},
                "loss_before": 1.0,
                "loss_after": 0.25,
            },
        )
        t["fitted_through"].append(angle_name(angle))
        t["models"][angle_name(angle)] = checkpoint_sha256(checkpoint)
    angles = sorted({angle_name(a) for a in models}, key=float)
    return {
        "format": UNIT_FORMAT,
        "unit_id": unit_id,
        "batches": [f"cal-{unit_id}"],
        "trials": [{"batch_id": f"cal-{unit_id}", "trial_id": f"a{a}-t01", "angle": a} for a in angles],
        "angles_used": angles,
        "angles_missing": [],
        "set_aside": [],
        "transforms": transforms,
        "params": {"transform": "full", "ridge": 0.01},
        "front_end": None,
        **({"cues": cues} if cues is not None else {}),
    }


def register_unit(uri: str, doc: dict) -> int:
    """Register `doc` in store `uri` as the register stage does: its version number (`@current`)."""
    return int(
        calibrations.register_unit(
            store.connect(uri),
            parse_unit(doc, "a test document"),
            calibrations.document_bytes(doc),
            lambda _m: None,
        )["version"]
    )
