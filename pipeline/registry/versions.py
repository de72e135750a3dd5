"""Registering: a candidate becomes a version of `needle-force-<angle>` and the aliases move by
the champion rule; `rollback` moves the champion back. `register_all` is what the stage runs: it
also registers the estimator units' calibrations (`pipeline.registry.calibrations`)."""

from __future__ import annotations

import contextlib
import json
import tempfile
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd

from needlecue_runtime.registry.store import (
    CHALLENGER,
    CHAMPION,
    EXPERIMENT,
    FORMAT_TAG,
    RegistryUnreachable,
    alias_version,
    create_registered_model,
    experiment_id,
    model_name,
    versions,
    writing,
)
from needlecue_runtime.vocab import AXES, DEPLOY_FORMAT, axes_of
from pipeline.config import RegisterParams
from pipeline.dataset.splits import SplitFiles
from pipeline.logs import Log
from pipeline.metrics.document import EVALUATION_FILE, read_evaluation
from pipeline.metrics.scores import mean_nrmse, shared_scores
from pipeline.modelling.checkpoint import CHECKPOINT_FILE, load_checkpoint
from pipeline.modelling.export import describe
from pipeline.modelling.prediction_store import Predictions
from pipeline.modelling.predictor import Predictor
from pipeline.modelling.split_predictions import predict_frame
from pipeline.registry.calibrations import load_documents, register_units
from pipeline.registry.candidates import Trained, collect, kind_rank
from pipeline.registry.champion import best_per_angle, decide
from pipeline.registry.tracking import TAG, Datasets, axes_words, deploy_sha256, git_commit, track

if TYPE_CHECKING:
    from mlflow import MlflowClient


def force_words(targets: Sequence[str]) -> str:
    """What a registered model gives: "3-D needle force (fx, fy, fz in N)", "Needle force (fz in N)"."""
    what = "3-D needle force" if list(targets) == list(AXES) else "Needle force"
    return f"{what} ({', '.join(targets)} in N)"


def rescore_version(
    client: MlflowClient, version: Any, external: pd.DataFrame, known: Mapping[str, float], log: Log
) -> float | None:
    """Mean NRMSE of a registered version on today's scored set. `known`: {model_sha256: score} of
    today's candidates, already scored from the stored predictions; any other version's checkpoint
    is fetched and predicted. None if its model cannot read this data (other channels, say): then it
    cannot defend its title. A checkpoint that cannot be fetched is an error (the stage fails and no
    alias moves), never a free pass."""
    import mlflow

    sha = version.tags.get(f"{TAG}model_sha256")
    if sha in known:
        return known[sha]
    with tempfile.TemporaryDirectory() as tmp:
        path = mlflow.artifacts.download_artifacts(
            run_id=version.run_id,
            artifact_path=f"checkpoint/{CHECKPOINT_FILE}",
            dst_path=tmp,
            tracking_uri=client.tracking_uri,
        )
        predictor = Predictor(load_checkpoint(Path(path)))
    # scored as today's candidates are (`candidates`): on the axes it gives that today's data recorded
    targets, recorded = list(predictor.targets), list(axes_of(external.columns))
    try:
        if not any(a in recorded for a in targets):
            raise ValueError(f"it gives {targets}, today's data records {recorded or 'no force axis'}")
        predicted = predict_frame(predictor, external, f"{version.name} v{version.version}")
    except (KeyError, ValueError) as e:
        log(f"{version.name} v{version.version}: cannot score today's data ({type(e).__name__}: {e})")
        return None
    return mean_nrmse(shared_scores(predicted, targets, external[recorded].to_numpy(np.float64), recorded))


def register_angle(
    client: MlflowClient,
    t: Trained,
    model_uri: str,
    run_id: str,
    deploy: str,
    external: pd.DataFrame,
    known: Mapping[str, float],
    params: RegisterParams,
    log: Log,
) -> dict[str, Any]:
    """Register `t` for its angle and move the aliases by the champion rule; the registry.json entry.
    `deploy`: the `deploy_sha256` of its graph and cue pack (a version is one deployable);
    `external`: the set `t` is judged on; `known`: today's candidates' scores on it, by model hash."""
    import mlflow

    name = model_name(float(t.angle))
    entry: dict[str, Any] = {
        "model": name,
        "kind": t.kind,
        "model_sha256": t.model_sha256,
        "external_nrmse_pct_mean": round(t.mean_nrmse(), 4),
        "scored_on": t.judged_on,
    }
    same = [v for v in versions(client, name) if v.tags.get(f"{TAG}deploy_sha256") == deploy]
    mv = max(same, key=lambda v: int(v.version)) if same else None
    if mv is not None:
        # search results may leave aliases out: ask for the version itself
        aliases = sorted(client.get_model_version(name, str(mv.version)).aliases or [])
        if aliases or mv.tags.get(f"{TAG}decided"):  # decided once (maybe since rolled back): final
            log(f"{name}: this {t.kind} is already version {mv.version} ({', '.join(aliases) or 'no alias'})")
            return {**entry, "action": "unchanged", "version": int(mv.version), "aliases": aliases}
        # registered by a run that was stopped before it set an alias: finish that decision now
        log(f"{name}: version {mv.version} was never decided (an interrupted run?): deciding it now")
    elif not versions(client, name):  # the first version creates the registered model: describe it
        create_registered_model(
            client,
            name,
            description=(
                f"{force_words(t.checkpoint['targets'])} from the estimator's voltages, "
                f"{t.angle}° insertions. "
                f"`@{CHAMPION}` is what the simulator loads (models:/{name}@{CHAMPION}); a new version "
                f"takes it only if it beats it on the external set, else it is `@{CHALLENGER}`. "
                "ONNX, no pickles; the cue pack is in the model's metadata."
            ),
        )
    champion = alias_version(client, name, CHAMPION)
    repack = champion is not None and champion.tags.get(f"{TAG}model_sha256") == t.model_sha256
    runnable = champion is not None and champion.tags.get(FORMAT_TAG) == DEPLOY_FORMAT
    if champion is not None and not runnable:  # today's clients refuse it: it cannot defend its title
        log(
            f"{name}: champion v{champion.version} is not registered as a {DEPLOY_FORMAT} graph, "
            "which clients run"
        )
    champion_score = (
        None
        if champion is None or repack or not runnable
        else rescore_version(client, champion, external, known, log)
    )
    if mv is None:
        run_tags = client.get_run(run_id).data.tags  # where the data behind it is: commit and dvc.lock
        provenance = {k: run_tags[k] for k in ("git_commit", f"{TAG}dvc_lock_sha256") if k in run_tags}
        mv = mlflow.register_model(
            model_uri,
            name,
            tags={
                f"{TAG}model_sha256": t.model_sha256,
                f"{TAG}deploy_sha256": deploy,
                FORMAT_TAG: DEPLOY_FORMAT,
                "model_type": t.kind,
                "angle_deg": t.angle,
                "external_nrmse_pct_mean": f"{t.mean_nrmse():.4f}",
                **provenance,
            },
        )
        client.update_model_version(
            name,
            mv.version,
            description=(
                f"{t.kind}, external NRMSE {t.mean_nrmse():.2f} % ({axes_words(t.checkpoint['targets'])}), "
                f"run {run_id}. " + describe(t.checkpoint)
            ),
        )
    decision = decide(
        t.mean_nrmse(),
        None if champion is None else int(champion.version),
        champion_score,
        params.min_improvement_pct,
        repack=repack,
    )
    alias, reason = decision.alias, decision.reason
    if decision.promote and champion is not None:
        client.set_model_version_tag(name, mv.version, f"{TAG}previous_champion", str(champion.version))
    client.set_registered_model_alias(name, alias, mv.version)
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
    with writing(uri) as client:  # a read-only store is refused before the alias moves
        name = model_name(angle_deg)
        champion = alias_version(client, name, CHAMPION)
        if to_version is None:
            if champion is None or not champion.tags.get(f"{TAG}previous_champion"):
                raise ValueError(f"{name}: no earlier champion on record; pass the version to roll back to")
            to_version = int(champion.tags[f"{TAG}previous_champion"])
        known = {int(v.version) for v in versions(client, name)}
        if to_version not in known:
            raise ValueError(f"{name} has no version {to_version} (versions: {sorted(known) or 'none'})")
        target = client.get_model_version(name, str(to_version))
        if target.tags.get(FORMAT_TAG) != DEPLOY_FORMAT:
            raise ValueError(
                f"{name} v{to_version} is not a {DEPLOY_FORMAT} graph: today's clients refuse it "
                "(register it again with `dvc repro`, or roll back to a newer version)"
            )
        client.set_registered_model_alias(name, CHAMPION, str(to_version))
        client.set_model_version_tag(
            name, str(to_version), f"{TAG}rolled_back_from", "" if champion is None else str(champion.version)
        )
        return (None if champion is None else int(champion.version)), to_version


def register_all(
    models_dir: Path,
    data_dir: Path,
    pred_dir: Path,
    reports_dir: Path,
    out_json: Path,
    params: RegisterParams,
    log: Log,
    cal_dir: Path | None = None,
) -> dict[str, Any]:
    """Track all models, register the best per angle, then every unit calibration in `cal_dir`
    (`<unit_id>.json`; none if None), write `out_json`; returns its content."""
    with contextlib.ExitStack() as scope:
        try:  # first: an unreachable, non-MLflow or read-only store changes nothing
            client = scope.enter_context(writing())
        except RegistryUnreachable as e:
            raise RegistryUnreachable(f"{e}\nNothing was registered and every alias is as it was.") from e
        documents = [] if cal_dir is None else load_documents(cal_dir)  # a bad one fails before any change
        metrics_path = reports_dir / EVALUATION_FILE
        metrics = read_evaluation(metrics_path) if metrics_path.is_file() else None
        figures = sorted((reports_dir / "figures").glob("*.png"))
        files = SplitFiles(data_dir)
        trained = collect(models_dir, files, Predictions(pred_dir), params.candidates, log)
        datasets = Datasets(files)
        commit = git_commit(Path.cwd())

        logged: dict[tuple[str, str], tuple[str, str, str]] = {}
        n_new = 0
        # Logged from the last angle and kind to the first, so the UI's newest-first list reads 0°-ls,
        # 0°-fnn, 0°-lstm, 15°-ls, ... from the top.
        trained.sort(key=lambda t: (float(t.angle), kind_rank(t.kind), t.kind), reverse=True)
        exp_id = experiment_id(client)
        for i, t in enumerate(trained, start=1):
            pack_path = reports_dir / "cues" / "packs" / f"{t.angle}.json"
            pack = json.loads(pack_path.read_text()) if pack_path.is_file() else None
            deploy = deploy_sha256(t.checkpoint, pack)
            run_id, uri, new = track(client, t, exp_id, datasets, metrics, pack, deploy, figures, commit, log)
            logged[(t.kind, t.angle)] = (run_id, uri, deploy)
            n_new += new
            if not new:
                log(f"[{i}/{len(trained)}] {t.angle}° {t.kind}: already tracked (run {run_id})")
        log(
            f"tracked {n_new} new run(s) of {len(trained)} model(s) in experiment {EXPERIMENT!r} "
            "(compare them: `needlecue ui`)"
        )

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
            run_id, uri, deploy = logged[(t.kind, t.angle)]
            split = t.judged_on
            known = {c.model_sha256: c.mean_nrmse(split) for c in trained if c.angle == angle}
            external = files.frame(angle, split)
            angles[angle] = register_angle(client, t, uri, run_id, deploy, external, known, params, log)
        angles = dict(sorted(angles.items(), key=lambda kv: float(kv[0])))
        units = register_units(client, documents, list(angles), log)
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
            "units": units["units"],
            "stale_units": units["stale_units"],
        }
        out_json.parent.mkdir(parents=True, exist_ok=True)
        out_json.write_text(json.dumps(record, indent=2, sort_keys=True) + "\n")
        return record
