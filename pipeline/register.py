"""`register` stage: track every trained model in MLflow and register the best one per angle.

1. Tracking. Each model folder `models/<kind>/<angle>` becomes one MLflow run of the experiment
   `needle-force`, named `<angle>°-<kind>`: its params, its loss curve (step = epoch), per-axis
   RMSE / NRMSE on the validation, test and external sets (`val_nrmse_pct_fx`, `test_rmse_fy`,
   `external_nrmse_pct_mean`, ...), the ±15°/±30° gap NRMSE, tags (angle, model type, git commit,
   data and model hashes), the report's figures, the checkpoint, and the deployable ONNX model with
   its signature and input example. A model already logged (same model hash) is not logged again.
2. Registering. Per angle, the best deployable candidate (`register.candidates`, lowest
   `external_nrmse_pct_mean`) becomes a new version of `needle-force-<angle>`, unless that exact
   model is already a version. It takes the `champion` alias only if it beats the current champion,
   re-scored on today's external set, by more than `register.min_improvement_pct`; otherwise it
   is the `challenger`.
3. `reports/registry.json` records per angle what was registered and promoted (no run ids or
   paths, so a fresh store gives the same file).

Usage: `python -m pipeline.register MODELS_DIR DATA_DIR REPORTS_DIR OUT_JSON [--params params.yaml]`.
`rollback()` backs `needlecue rollback` (moves the champion to an earlier version).
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
import warnings
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
import pandas as pd
import typer
from pydantic import Field

from pipeline.config import Section, load_section
from pipeline.evaluate import AXES, axis_scores, gap_of
from pipeline.export import checkpoint_sha256
from pipeline.models import KINDS
from pipeline.registry import (
    CHALLENGER,
    CHAMPION,
    EXPERIMENT,
    RegistryUnreachable,
    connect,
    experiment_id,
    model_name,
)

if TYPE_CHECKING:
    from mlflow import MlflowClient

Log = Callable[[str], None]
TAG = "needlecue."  # prefix of our own tags on runs and model versions
SPLITS = ("val", "test", "external")  # what each model is scored on


class RegisterParams(Section):
    """`register`: which models may be deployed and how a champion is chosen."""

    candidates: tuple[Literal["ls", "fnn", "lstm"], ...] = Field(("ls", "fnn", "lstm"), min_length=1)
    min_improvement_pct: float = Field(
        0.0, ge=0, description="NRMSE points (mean of axes) a new version must beat the champion by"
    )


def _stderr(msg: str) -> None:
    print(f"register: {msg}", file=sys.stderr, flush=True)


def _sorted_angles(names: list[str]) -> list[str]:
    return sorted(names, key=float)


@dataclass(frozen=True)
class Trained:
    """One model folder and what the pipeline measured of it."""

    kind: str
    angle: str
    folder: Path
    model_sha256: str  # export.checkpoint_sha256: identifies what the model computes, not the file's bytes
    checkpoint: dict[str, Any]
    train_metrics: dict[str, Any]
    scores: dict[str, dict[str, dict[str, float]]]  # split -> axis -> {"rmse", "nrmse_pct"}

    @property
    def judged_on(self) -> str | None:
        """The split the champion rule scores this model on: the external set, or the test split
        for an angle without external rows (as evaluate does); None when neither has rows."""
        for split in ("external", "test"):
            if all(np.isfinite(self.scores[split][a]["nrmse_pct"]) for a in AXES):
                return split
        return None

    def mean_nrmse(self, split: str | None = None) -> float:
        split = split or self.judged_on
        if split is None:
            return float("nan")
        return float(np.mean([self.scores[split][a]["nrmse_pct"] for a in AXES]))


class Splits:
    """Each angle's processed split files, each read once: scoring, the runs' dataset inputs and
    the champion's re-scoring all need them, for every model of the angle."""

    def __init__(self, data_dir: Path) -> None:
        self.data_dir = data_dir
        self._frames: dict[tuple[str, str], pd.DataFrame] = {}

    def path(self, angle: str, split: str) -> Path:
        return self.data_dir / angle / f"{split}.parquet"

    def frame(self, angle: str, split: str) -> pd.DataFrame:
        if (angle, split) not in self._frames:
            path = self.path(angle, split)
            if not path.is_file():
                raise FileNotFoundError(f"{path}: missing (run the split stage first)")
            self._frames[angle, split] = pd.read_parquet(path)
        return self._frames[angle, split]


def _kind_rank(kind: str) -> int:
    """ls, fnn, lstm (simplest first), then any other kind."""
    return KINDS.index(kind) if kind in KINDS else len(KINDS)


def _score(predictor: Any, frame: pd.DataFrame) -> dict[str, dict[str, float]]:
    if frame.empty:
        return {a: {"rmse": float("nan"), "nrmse_pct": float("nan")} for a in AXES}
    return axis_scores(predictor.predict(frame), frame[list(AXES)].to_numpy(np.float64))


def collect(
    models_dir: Path, splits: Splits, candidates: tuple[str, ...], log: Log = _stderr
) -> list[Trained]:
    """Every `models_dir/<kind>/<angle>` folder with a checkpoint, scored on its angle's splits."""
    from pipeline.models import Predictor, load_checkpoint

    out: list[Trained] = []
    for kind_dir in sorted(p for p in models_dir.iterdir() if p.is_dir()):
        for folder in sorted((p for p in kind_dir.iterdir() if p.is_dir()), key=lambda p: float(p.name)):
            checkpoint = load_checkpoint(folder)
            predictor = Predictor(checkpoint)
            scores = {split: _score(predictor, splits.frame(folder.name, split)) for split in SPLITS}
            metrics_file = folder / "train_metrics.json"
            train_metrics = json.loads(metrics_file.read_text()) if metrics_file.is_file() else {}
            out.append(
                Trained(
                    kind_dir.name,
                    folder.name,
                    folder,
                    checkpoint_sha256(checkpoint),
                    checkpoint,
                    train_metrics,
                    scores,
                )
            )
    if not out:
        raise FileNotFoundError(f"{models_dir}: no trained model folders (models/<kind>/<angle>/model.pt)")
    unknown = sorted({t.kind for t in out} - set(candidates))
    if unknown:
        log(f"not deployable by register.candidates, tracked only: {', '.join(unknown)}")
    return out


# --- tracking -----------------------------------------------------------------------------------


def run_metrics(t: Trained, metrics: Mapping[str, Any]) -> dict[str, float]:
    """The run's flat metrics: `<split>_<rmse|nrmse_pct>_<axis|mean>`, accuracy, gap NRMSE."""
    out: dict[str, float] = {}
    for split, scores in t.scores.items():
        for what in ("rmse", "nrmse_pct"):
            values = [scores[a][what] for a in AXES]
            out.update({f"{split}_{what}_{a}": v for a, v in zip(AXES, values, strict=True)})
            out[f"{split}_{what}_mean"] = float(np.mean(values))
    out["external_accuracy_pct"] = 100.0 - out["external_nrmse_pct_mean"]
    # This model on the other angles' external sets, averaged per gap (the paper's Table II, per model).
    row = metrics.get("angle_gap_matrix", {}).get(t.kind, {}).get(t.angle, {})
    for gap in metrics.get("gaps_deg", []):
        cells = [row[d] for d in row if abs(gap_of(t.angle, d) - float(gap)) < 1e-9]
        for a in AXES:
            vals = [c[a] for c in cells if c.get(a) is not None]
            if vals:
                out[f"gap{float(gap):g}_nrmse_pct_{a}"] = float(np.mean(vals))
    for key in ("best_epoch", "epochs_run", "best_val_loss"):
        if isinstance(t.train_metrics.get(key), int | float):
            out[key] = float(t.train_metrics[key])
    return {k: v for k, v in out.items() if np.isfinite(v)}


def run_params(t: Trained) -> dict[str, str]:
    ck = t.checkpoint
    params = {
        f"{t.kind}.{k}": json.dumps(v) if isinstance(v, list) else str(v) for k, v in ck["params"].items()
    }
    return {
        **params,
        "kind": t.kind,
        "angle_deg": t.angle,
        "channels": ",".join(ck["channels"]),
        "rate_hz": f"{ck['rate_hz']:g}",
        "window": str(ck["config"].get("window", 1)),
        "n_train": str(t.train_metrics.get("n_train", "")),
        "n_val": str(t.train_metrics.get("n_val", "")),
    }


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


def _loss_curve(t: Trained, path: Path) -> bool:
    history = t.folder / "history.csv"
    if not history.is_file():
        return False
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    h = pd.read_csv(history)
    fig, ax = plt.subplots(figsize=(5, 3.2))
    ax.plot(h["epoch"], h["train_loss"], label="train")
    if h["val_loss"].notna().any():
        ax.plot(h["epoch"], h["val_loss"], label="validation")
    ax.set(xlabel="epoch", ylabel="scaled MSE", yscale="log", title=f"{t.angle}° {t.kind}")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=90, metadata={"Software": None})
    plt.close(fig)
    return True


def find_run(client: MlflowClient, exp_id: str, sha: str) -> Any | None:
    """The latest run of the model with this hash, if any."""
    runs = client.search_runs(
        [exp_id],
        filter_string=f"tags.`{TAG}model_sha256` = '{sha}'",
        max_results=1,
        order_by=["attributes.start_time DESC"],
    )
    return runs[0] if runs else None


def track(
    client: MlflowClient,
    t: Trained,
    exp_id: str,
    splits: Splits,
    metrics: Mapping[str, Any],
    cue_pack: dict[str, Any] | None,
    figures: list[Path],
    commit: str,
    log: Log = _stderr,
) -> tuple[str, str, bool]:
    """Log `t` as a run (unless a run of the same model exists): (run_id, model_uri, newly_logged)."""
    import mlflow
    import mlflow.data
    from mlflow.entities import Metric

    from pipeline.export import log_onnx_model

    existing = find_run(client, exp_id, t.model_sha256)
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
        "mlflow.note.content": (
            f"{t.kind} for {t.angle}° insertions, trained on {t.train_metrics.get('n_train', '?')} samples; "
            f"external-set NRMSE (mean of fx, fy, fz) {t.mean_nrmse():.2f} %."
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
            frame = splits.frame(t.angle, split)
            if frame.empty:  # nothing to describe (and MLflow cannot digest an empty frame)
                continue
            with warnings.catch_warnings():  # MLflow registers its local-file source twice, then warns
                warnings.filterwarnings("ignore", message="The specified dataset source can be interpreted")
                dataset = mlflow.data.from_pandas(
                    frame, source=str(splits.path(t.angle, split)), name=f"{t.angle}°-{split}"
                )
            mlflow.log_input(dataset, context=context)
        mlflow.log_metrics(run_metrics(t, metrics))
        history = t.folder / "history.csv"
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
            if _loss_curve(t, curve):
                mlflow.log_artifact(str(curve), artifact_path="figures")
        for fig in figures:
            mlflow.log_artifact(str(fig), artifact_path="figures")
        for name in ("model.pt", "train_metrics.json", "history.csv"):
            if (t.folder / name).is_file():
                mlflow.log_artifact(str(t.folder / name), artifact_path="checkpoint")
        info = log_onnx_model(ck, cue_pack, name="model")
        mlflow.set_tag(f"{TAG}model_uri", info.model_uri)
    log(f"tracked {t.angle}° {t.kind}: run {run.info.run_id}, external NRMSE {t.mean_nrmse():.2f} %")
    return run.info.run_id, info.model_uri, True


# --- registering --------------------------------------------------------------------------------


def best_per_angle(trained: list[Trained], candidates: tuple[str, ...]) -> dict[str, Trained]:
    """The champion rule's first half: per angle, the candidate with the lowest mean external NRMSE
    (ties go to the simpler model, in the order ls, fnn, lstm)."""
    best: dict[str, Trained] = {}
    for t in trained:
        if t.kind not in candidates or t.judged_on is None:
            continue
        cur = best.get(t.angle)
        if cur is None or (t.mean_nrmse(), _kind_rank(t.kind)) < (cur.mean_nrmse(), _kind_rank(cur.kind)):
            best[t.angle] = t
    return dict(sorted(best.items(), key=lambda kv: float(kv[0])))


def _versions(client: MlflowClient, name: str) -> list[Any]:
    """Every version of `name` ([] for an unknown name); any other registry error propagates, so a
    hiccup of the store is never read as "no versions"."""
    return list(client.search_model_versions(f"name = '{name}'"))


def _alias_version(client: MlflowClient, name: str, alias: str) -> Any | None:
    """The version `name@alias` points to; None only when the model or the alias does not exist."""
    from mlflow.exceptions import MlflowException

    try:
        return client.get_model_version_by_alias(name, alias)
    except MlflowException as e:
        if e.error_code in ("RESOURCE_DOES_NOT_EXIST", "INVALID_PARAMETER_VALUE"):
            return None
        raise


def _create_registered_model(client: MlflowClient, name: str, description: str) -> None:
    """Create `name`; one left empty by an interrupted run is fine as it is."""
    from mlflow.exceptions import MlflowException

    try:
        client.create_registered_model(name, description=description)
    except MlflowException as e:
        if e.error_code != "RESOURCE_ALREADY_EXISTS":
            raise


def rescore_version(client: MlflowClient, version: Any, external: pd.DataFrame) -> float | None:
    """Mean external NRMSE of a registered version's checkpoint on today's external set; None if its
    model cannot read this data (other channels, say): then it cannot defend its title. A checkpoint
    that cannot be fetched is an error (the stage fails and no alias moves), never a free pass."""
    import mlflow

    from pipeline.models import Predictor, load_checkpoint

    with tempfile.TemporaryDirectory() as tmp:
        path = mlflow.artifacts.download_artifacts(
            run_id=version.run_id, artifact_path="checkpoint/model.pt", dst_path=tmp
        )
        predictor = Predictor(load_checkpoint(Path(path)))
    try:
        scores = _score(predictor, external)
    except (KeyError, ValueError) as e:
        _stderr(f"{version.name} v{version.version}: cannot score today's data ({type(e).__name__}: {e})")
        return None
    return float(np.mean([scores[a]["nrmse_pct"] for a in AXES]))


def register_angle(
    client: MlflowClient,
    t: Trained,
    model_uri: str,
    run_id: str,
    external: pd.DataFrame,
    params: RegisterParams,
    log: Log = _stderr,
) -> dict[str, Any]:
    """Register `t` for its angle and move the aliases by the champion rule; the registry.json entry."""
    import mlflow

    name = model_name(float(t.angle))
    entry: dict[str, Any] = {
        "model": name,
        "kind": t.kind,
        "model_sha256": t.model_sha256,
        "external_nrmse_pct_mean": round(t.mean_nrmse(), 4),
        "scored_on": t.judged_on,
    }
    same = [v for v in _versions(client, name) if v.tags.get(f"{TAG}model_sha256") == t.model_sha256]
    mv = max(same, key=lambda v: int(v.version)) if same else None
    if mv is not None:
        # search results may leave aliases out: ask for the version itself
        aliases = sorted(client.get_model_version(name, str(mv.version)).aliases or [])
        if aliases or mv.tags.get(f"{TAG}decided"):  # decided once (maybe since rolled back): final
            log(f"{name}: this {t.kind} is already version {mv.version} ({', '.join(aliases) or 'no alias'})")
            return {**entry, "action": "unchanged", "version": int(mv.version), "aliases": aliases}
        # registered by a run that was stopped before it set an alias: finish that decision now
        log(f"{name}: version {mv.version} was never decided (an interrupted run?): deciding it now")
    elif not _versions(client, name):  # the first version creates the registered model: describe it
        _create_registered_model(
            client,
            name,
            description=(
                f"3-D needle force (fx, fy, fz in N) from the estimator's voltages, {t.angle}° insertions. "
                f"`@{CHAMPION}` is what the simulator loads (models:/{name}@{CHAMPION}); a new version "
                f"takes it only if it beats it on the external set, else it is `@{CHALLENGER}`. "
                "ONNX, no pickles; the cue pack is in the model's metadata."
            ),
        )
    champion = _alias_version(client, name, CHAMPION)
    champion_score = None if champion is None else rescore_version(client, champion, external)
    if mv is None:
        mv = mlflow.register_model(
            model_uri,
            name,
            tags={
                f"{TAG}model_sha256": t.model_sha256,
                "model_type": t.kind,
                "angle_deg": t.angle,
                "external_nrmse_pct_mean": f"{t.mean_nrmse():.4f}",
            },
        )
        client.update_model_version(
            name,
            mv.version,
            description=f"{t.kind}, external NRMSE {t.mean_nrmse():.2f} % (mean of fx, fy, fz), run {run_id}",
        )
    if champion is None:
        promote, reason = True, "no champion yet"
    elif champion_score is None:
        promote, reason = True, f"champion v{champion.version} cannot be scored on today's external set"
    else:
        margin = champion_score - t.mean_nrmse()
        promote = margin > params.min_improvement_pct
        reason = (
            f"external NRMSE {t.mean_nrmse():.3f} % vs champion v{champion.version} {champion_score:.3f} % "
            f"({'better' if margin > 0 else 'not better'} by {abs(margin):.3f}, "
            f"needed > {params.min_improvement_pct:g})"
        )
    if promote:
        if champion is not None:
            client.set_model_version_tag(name, mv.version, f"{TAG}previous_champion", str(champion.version))
        client.set_registered_model_alias(name, CHAMPION, mv.version)
        alias = CHAMPION
    else:
        client.set_registered_model_alias(name, CHALLENGER, mv.version)
        alias = CHALLENGER
    # Marks the decision as made: a later rollback (or a newer challenger) may take the alias away,
    # and the next run must not mistake that for an interrupted decision and re-promote it.
    client.set_model_version_tag(name, mv.version, f"{TAG}decided", alias)
    log(f"{name}: registered {t.kind} as version {mv.version} -> {alias} ({reason})")
    out = {**entry, "action": "registered", "version": int(mv.version), "aliases": [alias], "reason": reason}
    if champion is not None:
        out["previous_champion"] = {
            "version": int(champion.version),
            "external_nrmse_pct_mean": None if champion_score is None else round(champion_score, 4),
        }
    return out


def rollback(
    angle_deg: float, to_version: int | None = None, uri: str | None = None
) -> tuple[int | None, int]:
    """Move `needle-force-<angle>@champion` to `to_version` (default: the version the current champion
    replaced). Returns (old champion version, new champion version)."""
    client = connect(uri)
    name = model_name(angle_deg)
    champion = _alias_version(client, name, CHAMPION)
    if to_version is None:
        if champion is None or not champion.tags.get(f"{TAG}previous_champion"):
            raise ValueError(f"{name}: no earlier champion on record; pass the version to roll back to")
        to_version = int(champion.tags[f"{TAG}previous_champion"])
    known = {int(v.version) for v in _versions(client, name)}
    if to_version not in known:
        raise ValueError(f"{name} has no version {to_version} (versions: {sorted(known) or 'none'})")
    client.set_registered_model_alias(name, CHAMPION, str(to_version))
    client.set_model_version_tag(
        name, str(to_version), f"{TAG}rolled_back_from", "" if champion is None else str(champion.version)
    )
    return (None if champion is None else int(champion.version)), to_version


# --- the stage ----------------------------------------------------------------------------------


def run(
    models_dir: Path,
    data_dir: Path,
    reports_dir: Path,
    out_json: Path,
    params: RegisterParams,
    log: Log = _stderr,
) -> dict[str, Any]:
    """Track all models, register the best per angle, write `out_json`; returns its content."""
    try:
        client = connect()  # before anything else: an unreachable store changes nothing
    except RegistryUnreachable as e:
        raise RegistryUnreachable(f"{e}\nNothing was registered and every alias is as it was.") from e
    metrics_path = reports_dir / "metrics.json"
    metrics = json.loads(metrics_path.read_text()) if metrics_path.is_file() else {}
    figures = sorted((reports_dir / "figures").glob("*.png"))
    splits = Splits(data_dir)
    trained = collect(models_dir, splits, params.candidates, log)
    commit = git_commit(Path.cwd())

    logged: dict[tuple[str, str], tuple[str, str]] = {}
    n_new = 0
    # Logged from the last angle and kind to the first, so the UI's newest-first list reads 0°-ls,
    # 0°-fnn, 0°-lstm, 15°-ls, ... from the top.
    trained.sort(key=lambda t: (float(t.angle), _kind_rank(t.kind), t.kind), reverse=True)
    exp_id = experiment_id(client)
    for i, t in enumerate(trained, start=1):
        pack_path = reports_dir / "cues" / "packs" / f"{t.angle}.json"
        pack = json.loads(pack_path.read_text()) if pack_path.is_file() else None
        run_id, uri, new = track(client, t, exp_id, splits, metrics, pack, figures, commit, log)
        logged[(t.kind, t.angle)] = (run_id, uri)
        n_new += new
        if not new:
            log(f"[{i}/{len(trained)}] {t.angle}° {t.kind}: already tracked (run {run_id})")
    log(f"tracked {n_new} new run(s) of {len(trained)} model(s) in experiment {EXPERIMENT!r}")

    angles: dict[str, Any] = {}
    best = best_per_angle(trained, params.candidates)
    for angle in sorted({t.angle for t in trained} - set(best), key=float):
        reason = "no external or test rows to score a candidate on: nothing registered"
        log(f"{model_name(float(angle))}: {reason}")
        angles[angle] = {
            "model": model_name(float(angle)),
            "action": "skipped",
            "aliases": [],
            "reason": reason,
        }
    for angle, t in best.items():
        run_id, uri = logged[(t.kind, t.angle)]
        angles[angle] = register_angle(client, t, uri, run_id, splits.frame(angle, t.judged_on), params, log)
    angles = dict(sorted(angles.items(), key=lambda kv: float(kv[0])))
    record = {
        "experiment": EXPERIMENT,
        "rule": {
            "candidates": list(params.candidates),
            "best": "lowest external_nrmse_pct_mean (mean of fx, fy, fz NRMSE on the external set)",
            "promote": "beats the champion, re-scored on the same external set, "
            f"by > {params.min_improvement_pct:g} NRMSE points",
        },
        "angles": angles,
        "registered": sorted((a for a, e in angles.items() if e["action"] == "registered"), key=float),
        "promoted": sorted(
            (a for a, e in angles.items() if CHAMPION in e["aliases"] and e["action"] == "registered"),
            key=float,
        ),
    }
    out_json.parent.mkdir(parents=True, exist_ok=True)
    out_json.write_text(json.dumps(record, indent=2, sort_keys=True) + "\n")
    return record


def main(
    models_dir: Path,
    data_dir: Path,
    reports_dir: Path,
    out_json: Path,
    params: Path = Path("params.yaml"),
) -> None:
    """Track every trained model in MLflow and register the best per angle (champion / challenger)."""
    from mlflow.exceptions import MlflowException

    p = load_section(RegisterParams, "register", params)
    try:
        record = run(models_dir, data_dir, reports_dir, out_json, p)
    except RegistryUnreachable as e:
        _stderr(f"error: {e}")
        raise typer.Exit(1) from e
    except (FileNotFoundError, ValueError) as e:
        _stderr(f"error: {e}")
        raise typer.Exit(1) from e
    except MlflowException as e:  # the store answered, then failed: no alias moved after the failure
        _stderr(f"error: MLflow registry ({e.error_code}): {e.message}")
        raise typer.Exit(1) from e
    _stderr(
        f"registered {len(record['registered'])} angle(s), promoted {len(record['promoted'])} -> {out_json}"
    )


if __name__ == "__main__":
    typer.run(main)
