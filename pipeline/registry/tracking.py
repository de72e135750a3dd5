"""Tracking: each trained model as one MLflow run of the `needle-force` experiment, with its
params, datasets, loss curve, per-split and per-gap metrics, figures, checkpoint and the deployable
ONNX model with its cue pack. A deployable already tracked (the same model with the same cue pack:
`deploy_sha256`) is not logged again."""

from __future__ import annotations

import contextlib
import hashlib
import json
import subprocess
import tempfile
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd

from needlecue_runtime.registry.store import TAG, finished_run
from needlecue_runtime.vocab import DEPLOY_FORMAT, axes_of
from pipeline.dataset.splits import SplitFiles
from pipeline.logs import Log
from pipeline.metrics.document import Evaluation
from pipeline.metrics.scores import gap_of
from pipeline.modelling.checkpoint import CHECKPOINT_FILE, HISTORY_FILE, METRICS_FILE, checkpoint_meta
from pipeline.registry.candidates import Trained
from pipeline.reporting.loss import loss_curve_png

if TYPE_CHECKING:
    from mlflow import MlflowClient


def run_metrics(t: Trained, metrics: Evaluation | None) -> dict[str, float]:
    """The run's flat metrics: `<split>_<rmse|nrmse_pct>_<axis|mean>`, accuracy, gap NRMSE, and the
    cues of its kind (`cues_<group>_<balanced_within_s|wrong_final|wrong_frames|...>_pct`); without an
    evaluation (`metrics` None), its own scores only. The axes are those the scores have (the model's
    targets: a model of fz alone logs `..._fz` and a mean over fz); none is logged for an axis the
    reference did not record."""
    out: dict[str, float] = {}
    for split, scores in t.scores.items():
        axes = axes_of(scores)
        for what in ("rmse", "nrmse_pct"):
            values = [scores[a][what] for a in axes]
            out.update({f"{split}_{what}_{a}": v for a, v in zip(axes, values, strict=True)})
            out[f"{split}_{what}_mean"] = float(np.mean(values)) if values else float("nan")
    out["external_accuracy_pct"] = 100.0 - out["external_nrmse_pct_mean"]
    # This model on the other angles' external sets, averaged per gap (the paper's Table II, per model).
    row = {} if metrics is None else metrics.angle_gap_matrix.get(t.kind, {}).get(t.angle, {})
    for gap in [] if metrics is None else metrics.gaps_deg:
        cells = [row[d] for d in row if abs(gap_of(t.angle, d) - float(gap)) < 1e-9]
        for a in t.checkpoint["targets"]:
            vals = [c[a] for c in cells if c.get(a) is not None]
            if vals:
                out[f"gap{float(gap):g}_nrmse_pct_{a}"] = float(np.mean(vals))
    # What a trainee sees with this kind's cues, over every preset angle (evaluation.json "cues")
    for group, figures in ({} if metrics is None else metrics.cues.get(t.kind, {})).items():
        for what, v in figures.model_dump().items():
            if v is not None and what != "trials":
                out[f"cues_{group}_{what}_pct"] = float(v)
    for key in ("best_epoch", "epochs_run", "best_val_loss"):
        if isinstance(t.train_metrics.get(key), int | float):
            out[key] = float(t.train_metrics[key])
    return {k: v for k, v in out.items() if np.isfinite(v)}


def axes_words(targets: Sequence[str]) -> str:
    """How a figure averaged over `targets` is named: "mean of fx, fy, fz", or "fz" for one axis."""
    return targets[0] if len(targets) == 1 else f"mean of {', '.join(targets)}"


def run_params(t: Trained) -> dict[str, str]:
    ck = checkpoint_meta(t.checkpoint, f"the {t.kind} checkpoint at {t.angle}°")
    params = {f"{t.kind}.{k}": json.dumps(v) if isinstance(v, list) else str(v) for k, v in ck.params.items()}
    inputs, choice = ck.inputs or {}, ck.inputs_choice or {}
    return {
        **params,
        "kind": t.kind,
        "angle_deg": t.angle,
        "channels": ",".join(ck.channels),
        "rate_hz": f"{ck.rate_hz:g}",
        "window": str(ck.config.window),
        "n_train": str(t.train_metrics.get("n_train", "")),
        "n_val": str(t.train_metrics.get("n_val", "")),
        # what it reads, and how that was chosen (pinned in params, or by validation: the scores)
        "inputs": str(inputs.get("kind", "volts")),
        "inputs_chosen_by": "params" if not choice else str(choice["folds"]),
        **{
            f"inputs_score_{k}": "n/a" if v is None else f"{v:g}"
            for k, v in (choice.get("scores") or {}).items()
        },
    }


LOCK_ARTIFACT = "dvc/dvc.lock"  # a run's copy of dvc.lock at registration (pipeline.registry.provenance)


def git_commit(root: Path) -> str:
    """HEAD's commit (with "+dirty" if the work tree differs), or "unknown" outside git."""
    try:
        head = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True, check=True
        )
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            cwd=root,
            capture_output=True,
            text=True,
            check=True,
        )
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return head.stdout.strip() + ("+dirty" if dirty.stdout.strip() else "")


class Datasets:
    """The MLflow datasets of the split files, each described once (the kinds of one angle log the
    same four sets), with the schema `frame_schema` computes. The same object logged again gives the
    same record."""

    def __init__(self, files: SplitFiles) -> None:
        self.files = files
        self._made: dict[tuple[str, str], Any] = {}

    def get(self, angle: str, split: str) -> Any | None:
        """The dataset of one split file, None when it has no rows (MLflow cannot digest those)."""
        if (angle, split) not in self._made:
            import mlflow.data

            frame = self.files.frame(angle, split)
            dataset = None
            if not frame.empty:
                with warnings.catch_warnings():  # MLflow registers its local-file source twice, then warns
                    warnings.filterwarnings(
                        "ignore", message="The specified dataset source can be interpreted"
                    )
                    dataset = mlflow.data.from_pandas(
                        frame, source=str(self.files.path(angle, split)), name=f"{angle}°-{split}"
                    )
                # MLflow computes the schema when the dataset is logged (a cached property): ours
                # first; a frame it cannot take is left to MLflow, which then says None (no schema)
                with contextlib.suppress(Exception):
                    dataset.__dict__["schema"] = frame_schema(frame)
            self._made[(angle, split)] = dataset
        return self._made[(angle, split)]

    def example_trial(self, angle: str, channels: list[str]) -> tuple[np.ndarray, np.ndarray] | None:
        """A real trial of the angle for a model's input example: raw volts (n, C) and times, the first
        trial of the test split (else of the external set); None without one."""
        for split in ("test", "external"):
            with contextlib.suppress(FileNotFoundError):
                frame = self.files.frame(angle, split)
                if not frame.empty and all(c in frame.columns for c in channels):
                    first = frame.iloc[0]
                    same = (frame["batch_id"] == first["batch_id"]) & (frame["trial_id"] == first["trial_id"])
                    trial = frame[same].sort_values("t_s")
                    return trial[channels].to_numpy(np.float64), trial["t_s"].to_numpy(np.float64)
        return None


def frame_schema(frame: pd.DataFrame) -> Any:
    """MLflow's schema of a split file's frame (`mlflow.types.utils._infer_schema`), a column at a
    time. MLflow's own tests each value in Python for whether the column may be missing: 0.16 s for
    one 14k-row training split, a fifth of the register stage for the 24 split files. For number,
    boolean and string columns that test is `isna` (a missing float is NaN, a missing string NaN or
    NA, an integer never missing), and the type follows from the dtype, or for strings from a value;
    any other column is MLflow's to infer. A test compares the two."""
    from mlflow.types import ColSpec, Schema
    from mlflow.types.utils import _infer_schema

    specs = []
    for name in frame.columns:
        column = frame[name]
        typed = isinstance(column.dtype, np.dtype) and column.dtype.kind in "biuf"
        present = column.notna()
        if typed or (isinstance(column.dtype, pd.StringDtype) and present.any()):
            first = frame[[name]][present].iloc[:1] if not typed else frame[[name]].iloc[:1]
            kind = _infer_schema(first).inputs[0].type
            specs.append(ColSpec(type=kind, name=name, required=bool(present.all())))
        else:
            specs.append(_infer_schema(frame[[name]]).inputs[0])
    return Schema(specs)


def deploy_sha256(checkpoint: dict[str, Any], cue_pack: Mapping[str, Any] | None) -> str:
    """What a simulator gets from a version: the graph exported from the model (its bytes: a new
    export of the same weights, say one that reads the estimator's raw readings, is a new
    deployable), the cue pack in its metadata (new cues must reach the simulators) and the format."""
    from pipeline.modelling.export import to_onnx

    graph = hashlib.sha256(to_onnx(checkpoint)).hexdigest()
    doc = {"graph_sha256": graph, "cues": cue_pack, "format": DEPLOY_FORMAT}
    text = json.dumps(doc, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()


def track(
    client: MlflowClient,
    t: Trained,
    exp_id: str,
    datasets: Datasets,
    metrics: Evaluation | None,
    cue_pack: dict[str, Any] | None,
    deploy: str,
    figures: list[Path],
    commit: str,
    log: Log,
) -> tuple[str, str, bool]:
    """Log `t` with `cue_pack` as a run, unless a finished run of the same deployable (`deploy`, its
    `deploy_sha256`) exists: (run_id, model_uri, newly_logged)."""
    import mlflow
    from mlflow.entities import Metric

    from pipeline.modelling.export import log_onnx_model

    existing = finished_run(client, exp_id, f"{TAG}deploy_sha256", deploy)
    if existing is not None and existing.data.tags.get(f"{TAG}model_uri"):
        return existing.info.run_id, existing.data.tags[f"{TAG}model_uri"], False

    ck = t.checkpoint
    tags = {
        "angle_deg": t.angle,
        "model_type": t.kind,
        "deployable": "true",  # every kind here reads estimator voltages only
        "git_commit": commit,
        "data_sha256": str(ck.get("train_data_sha256", "")),
        f"{TAG}model_sha256": t.model_sha256,
        f"{TAG}deploy_sha256": deploy,
        "mlflow.note.content": (
            f"{t.kind} for {t.angle}° insertions, trained on {t.train_metrics.get('n_train', '?')} samples; "
            f"external-set NRMSE ({axes_words(ck['targets'])}) {t.mean_nrmse():.2f} %."
        ),
    }
    with mlflow.start_run(experiment_id=exp_id, run_name=f"{t.angle}°-{t.kind}", tags=tags) as run:
        mlflow.log_params(run_params(t))
        for split, context in (
            ("train", "training"),
            ("val", "validation"),
            ("test", "test"),
            ("external", "external"),
        ):
            dataset = datasets.get(t.angle, split)
            if dataset is not None:
                mlflow.log_input(dataset, context=context)
        # The model before the metrics: MLflow links the metrics a run has at step 0 to a model logged
        # in it by fetching each one's history, a request per metric (about 60 of the 110 s that 18
        # models took on the team server), and logging them again with the model's id. Logged with
        # that id once the model is there, they are the run's metrics and the model's in one request.
        trial = datasets.example_trial(t.angle, list(ck["channels"]))
        info = log_onnx_model(ck, cue_pack, name="model", trial=trial)
        mlflow.log_metrics(run_metrics(t, metrics), model_id=info.model_id)
        history = t.folder / HISTORY_FILE
        if history.is_file():
            h = pd.read_csv(history)
            steps = [
                Metric(key, float(v), 0, int(e))
                for key in ("train_loss", "val_loss")
                for e, v in zip(h["epoch"], h[key], strict=True)
                if pd.notna(v)
            ]
            for i in range(0, len(steps), 1000):  # log_batch takes at most 1000 metrics a call
                client.log_batch(run.info.run_id, metrics=steps[i : i + 1000])
        with tempfile.TemporaryDirectory() as tmp:
            curve = Path(tmp) / "loss_curve.png"
            if loss_curve_png(t.folder / HISTORY_FILE, f"{t.angle}° {t.kind}", curve):
                mlflow.log_artifact(str(curve), artifact_path="figures")
        for fig in figures:
            mlflow.log_artifact(str(fig), artifact_path="figures")
        for name in (CHECKPOINT_FILE, METRICS_FILE, HISTORY_FILE):
            if (t.folder / name).is_file():
                mlflow.log_artifact(str(t.folder / name), artifact_path="checkpoint")
        lock = Path("dvc.lock")  # the stages before this one, as DVC recorded them: the exact data
        if lock.is_file():
            mlflow.log_artifact(str(lock), artifact_path=LOCK_ARTIFACT.rsplit("/", 1)[0])
            mlflow.set_tag(f"{TAG}dvc_lock_sha256", hashlib.sha256(lock.read_bytes()).hexdigest())
        mlflow.set_tag(f"{TAG}model_uri", info.model_uri)
    log(f"tracked {t.angle}° {t.kind}: run {run.info.run_id}, external NRMSE {t.mean_nrmse():.2f} %")
    return run.info.run_id, info.model_uri, True
