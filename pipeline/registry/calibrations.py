"""Estimator units in the registry: each unit's calibration document (needlecue-unit/4, built by
`pipeline.calibration.unit`) as a run of the experiment `needle-units` and a version of
`needle-unit-<unit_id>`, alias `@current`; which units' calibrations the current champions have
outgrown (stale); and the champions' checkpoints that `needlecue calibrate` fits a new unit through.

A version's source is the run's plain artifact folder `calibration/` (holding `calibration.json`):
MLflow 3 registers any artifact URI as a version, downloads it by `models:/needle-unit-<id>/<v>`, and
the client reads the JSON with no MLflow flavour. A document is registered once: its sha256 (of its
bytes) is the version tag `needlecue.calibration_sha256`, and a run already holding those bytes is
reused. mlflow, torch and the model code are imported inside the functions that need them.
"""

from __future__ import annotations

import hashlib
import json
import tempfile
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

from needlecue_runtime.registry.store import (
    CALIBRATION_SHA_TAG,
    CHAMPION,
    UNIT_ABOUT,
    UNIT_ALIAS,
    UNIT_EXPERIMENT,
    alias_version,
    create_registered_model,
    experiment_id,
    finished_run,
    mlmodel_metadata,
    unit_model_name,
    versions,
)
from needlecue_runtime.unit_calibration import FILE, UnitCalibration, read_unit, transform_for, unit_text
from needlecue_runtime.vocab import DEPLOY_FORMAT, angle_name, sorted_angles
from pipeline.logs import Log

if TYPE_CHECKING:
    from mlflow import MlflowClient

    from pipeline.modelling.predictor import Predictor

SHA_TAG = CALIBRATION_SHA_TAG
ARTIFACT_DIR = "calibration"  # the run's artifact folder that a unit version is made from
ADVICE = "run needlecue calibrate"
FORCE_PREFIX = "needle-force-"


def document_bytes(doc: Mapping[str, Any]) -> bytes:
    """A document as `write_unit` writes it (the bytes whose sha256 names it)."""
    return unit_text(doc).encode()


def sha256_of(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


# --------------------------------------------------------------------------- the champions


def champion_models(
    client: MlflowClient, angles: Iterable[str] | None = None, log: Log | None = None
) -> dict[str, dict[str, Any]]:
    """{angle: {"name", "version", "run_id", "kind", "format", "checkpoint_sha256"}} of every
    `needle-force-<angle>@champion` (only `angles` if given), read from its MLmodel metadata. A champion
    without an MLmodel, or with one that is not an MLmodel, is left out and said to `log`: one broken
    version does not stop the other angles. A registry that fails to answer is raised, as ever."""
    wanted = None if angles is None else {angle_name(a) for a in angles}
    names: list[str] = []
    token = None
    while True:
        page = client.search_registered_models(
            filter_string=f"name LIKE '{FORCE_PREFIX}%'", max_results=100, page_token=token
        )
        names += [m.name for m in page]
        token = page.token
        if not token:
            break
    out: dict[str, dict[str, Any]] = {}
    for name in names:
        suffix = name.removeprefix(FORCE_PREFIX)
        try:
            angle = angle_name(suffix)
        except ValueError:
            continue
        if (wanted is not None and angle not in wanted) or angle != suffix:
            continue
        mv = alias_version(client, name, CHAMPION)
        if mv is None:
            continue
        meta = _mlmodel_metadata(client, name, str(mv.version))
        if isinstance(meta, str):
            if log is not None:
                log(f"{name} v{mv.version} (@{CHAMPION}): {meta}: left out")
            continue
        block = meta.get("needlecue") or {}
        out[angle] = {
            "name": name,
            "version": int(mv.version),
            "run_id": mv.run_id,
            "kind": block.get("kind"),
            "format": block.get("format"),
            "checkpoint_sha256": block.get("checkpoint_sha256"),
        }
    return {a: out[a] for a in sorted_angles(out)}


def _mlmodel_metadata(client: MlflowClient, name: str, version: str) -> dict[str, Any] | str:
    """The `metadata` mapping of a version's MLmodel, or why there is none (the version has no MLmodel,
    or it is not YAML or not an MLmodel). The version's files are listed first: MLflow's own download
    reports a failed transfer of some sources as a missing file, and an outage must not look like that."""
    import mlflow

    root = client.get_model_version_download_uri(name, version).rstrip("/")
    listed = mlflow.artifacts.list_artifacts(artifact_uri=root, tracking_uri=client.tracking_uri)
    if not any(f.path.rsplit("/", 1)[-1] == "MLmodel" and not f.is_dir for f in listed):
        return f"no MLmodel among its files ({root})"
    with tempfile.TemporaryDirectory() as tmp:
        path = mlflow.artifacts.download_artifacts(
            artifact_uri=f"{root}/MLmodel", dst_path=tmp, tracking_uri=client.tracking_uri
        )
        try:
            return mlmodel_metadata(Path(path))
        except ValueError as e:
            return f"its MLmodel: {e}"


def uncovered_angles(doc: UnitCalibration, champions: Mapping[str, Mapping[str, Any]]) -> list[str]:
    """The champions' angles whose model the unit's document does not calibrate (made with other
    models, or with no transform for the champion's kind)."""
    return [
        angle
        for angle, c in champions.items()
        if transform_for(doc, str(c.get("kind")), angle, str(c.get("checkpoint_sha256"))) is None
    ]


def champion_predictors(
    client: MlflowClient, champions: Mapping[str, Mapping[str, Any]], log: Log
) -> dict[str, dict[str, Predictor]]:
    """{kind: {angle: Predictor}} of the champions, each loaded from the checkpoint its run logged
    (`checkpoint/model.pt`: the registered version itself holds the ONNX graph only) and checked to be
    the registered model (same checkpoint_sha256 as its metadata). A champion whose checkpoint cannot
    be fetched, or that is of an older deploy format (which clients no longer run), is left out with a
    message."""
    import mlflow
    from mlflow.exceptions import MlflowException

    from pipeline.modelling.checkpoint import CHECKPOINT_FILE, checkpoint_sha256, load_checkpoint
    from pipeline.modelling.predictor import Predictor

    out: dict[str, dict[str, Predictor]] = {}
    for angle, c in champions.items():
        what = f"{c['name']} v{c['version']} ({c['kind']})"
        if c.get("format") != DEPLOY_FORMAT:
            log(f"{what}: a {c.get('format')} model, which clients no longer run (register it again)")
            continue
        if not c.get("run_id"):
            log(f"{what}: no run to fetch its checkpoint from: left out")
            continue
        with tempfile.TemporaryDirectory() as tmp:
            try:
                path = mlflow.artifacts.download_artifacts(
                    run_id=c["run_id"],
                    artifact_path=f"checkpoint/{CHECKPOINT_FILE}",
                    dst_path=tmp,
                    tracking_uri=client.tracking_uri,
                )
                checkpoint = load_checkpoint(Path(path))
            except (MlflowException, OSError) as e:
                log(f"{what}: its run {c['run_id']} has no checkpoint/{CHECKPOINT_FILE} ({e}): left out")
                continue
        if checkpoint_sha256(checkpoint) != c.get("checkpoint_sha256"):
            log(f"{what}: the checkpoint its run logged is not the registered model: left out")
            continue
        out.setdefault(str(c["kind"]), {})[angle] = Predictor(checkpoint)
    return out


# --------------------------------------------------------------------------- registering


def _describe(name: str, unit_id: str) -> str:
    return (
        f"Calibration of estimator unit {unit_id}: per model kind, the input transform that lets "
        f"the shared needle-force models read this unit (needlecue-unit/4, `{FILE}`). "
        f"`@{UNIT_ALIAS}` is what the simulator applies (models:/{name}@{UNIT_ALIAS}); a "
        "transform applies only to the models it was fitted through (their checkpoint sha256)."
    )


def _log_run(client: MlflowClient, exp_id: str, doc: UnitCalibration, data: bytes, sha: str) -> Any:
    """One run of `needle-units`: params, loss metrics, tags, and the document as an artifact."""
    from mlflow.entities import Metric, Param, RunTag

    unit_id = doc.unit_id
    tags = {
        "unit_id": unit_id,
        "batches": ",".join(doc.batches),
        "angles_used": ",".join(doc.angles_used),
        "angles_missing": ",".join(doc.angles_missing),
        "kinds": ",".join(sorted(doc.transforms)),
        SHA_TAG: sha,
        "mlflow.note.content": (
            f"Calibration of estimator unit {unit_id} from {len(doc.trials)} trial(s) at "
            f"{', '.join(doc.angles_used) or 'no'}°."
        ),
    }
    run = client.create_run(exp_id, run_name=f"unit {unit_id}", tags=tags)
    run_id = run.info.run_id
    try:
        params = [Param(k, v if isinstance(v, str) else json.dumps(v)) for k, v in sorted(doc.params.items())]
        metrics = [
            Metric(f"{kind}_{key}", value, 0, 0)
            for kind, t in sorted(doc.transforms.items())
            for key, value in (("loss_before", t.loss_before), ("loss_after", t.loss_after))
            if value is not None
        ]
        client.log_batch(run_id, metrics=metrics, params=params, tags=[RunTag(k, v) for k, v in tags.items()])
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / FILE
            path.write_bytes(data)
            client.log_artifact(run_id, str(path), artifact_path=ARTIFACT_DIR)
    except BaseException:
        client.set_terminated(run_id, "FAILED")
        raise
    client.set_terminated(run_id, "FINISHED")
    return client.get_run(run_id)


def register_unit(client: MlflowClient, doc: UnitCalibration, data: bytes, log: Log) -> dict[str, Any]:
    """Register the document `doc` (whose file bytes are `data`) as a version of
    `needle-unit-<unit_id>` and move `@current` to it; registry.json's entry {version, action, aliases}.

    Already a version (same sha256): not registered again; `@current` is set to it only when it has
    none or points to an older version (a registration interrupted before the alias), never moved
    back from a newer calibration."""
    unit_id = doc.unit_id
    name = unit_model_name(unit_id)
    sha = sha256_of(data)
    known = versions(client, name)
    same = [v for v in known if v.tags.get(SHA_TAG) == sha]
    current = alias_version(client, name, UNIT_ALIAS)
    if same:
        mv = max(same, key=lambda v: int(v.version))
        if current is None or int(current.version) < int(mv.version):
            client.set_registered_model_alias(name, UNIT_ALIAS, str(mv.version))
            log(f"{name}: this calibration is already version {mv.version}: @{UNIT_ALIAS} set to it")
            return {"version": int(mv.version), "action": "alias_set", "aliases": [UNIT_ALIAS]}
        aliases = sorted(client.get_model_version(name, str(mv.version)).aliases or [])
        where = "" if int(current.version) == int(mv.version) else f", @{UNIT_ALIAS} is v{current.version}"
        log(f"{name}: this calibration is already version {mv.version}{where}")
        return {"version": int(mv.version), "action": "unchanged", "aliases": aliases}
    if not known:
        create_registered_model(client, name, _describe(name, unit_id))
    exp_id = experiment_id(client, UNIT_EXPERIMENT, UNIT_ABOUT)
    run = finished_run(client, exp_id, SHA_TAG, sha) or _log_run(client, exp_id, doc, data, sha)
    losses = ", ".join(
        f"{kind} {t.loss_before:.4g} -> {t.loss_after:.4g}"
        for kind, t in sorted(doc.transforms.items())
        if t.loss_before is not None and t.loss_after is not None
    )
    mv = client.create_model_version(
        name,
        source=f"{run.info.artifact_uri}/{ARTIFACT_DIR}",
        run_id=run.info.run_id,
        tags={SHA_TAG: sha, "unit_id": unit_id, "angles_used": ",".join(doc.angles_used)},
        description=f"calibration of {unit_id} at {', '.join(doc.angles_used) or 'no'}°"
        + (f"; loss {losses}" if losses else ""),
    )
    client.set_registered_model_alias(name, UNIT_ALIAS, str(mv.version))
    log(f"{name}: registered version {mv.version} -> @{UNIT_ALIAS} (run {run.info.run_id})")
    return {"version": int(mv.version), "action": "registered", "aliases": [UNIT_ALIAS]}


def load_documents(cal_dir: Path) -> list[tuple[UnitCalibration, bytes]]:
    """Every `cal_dir/<unit_id>.json` as (document, its bytes), checked (ValueError naming a bad
    file); none if the folder does not exist."""
    cal_dir = Path(cal_dir)
    files = sorted(cal_dir.glob("*.json")) if cal_dir.is_dir() else []
    return [(read_unit(f), f.read_bytes()) for f in files]


def register_units(
    client: MlflowClient,
    documents: list[tuple[UnitCalibration, bytes]],
    angles: Iterable[str] | None,
    log: Log,
) -> dict[str, Any]:
    """Register every unit's calibration document (`load_documents`) and check it against the
    current champions (of `angles`, or every registered angle): registry.json's {"units": {unit_id:
    entry}, "stale_units": {unit_id: {"angles", "advice"}}}. A stale unit (its calibration made with
    other models than a champion's) is reported, never an error."""
    units: dict[str, Any] = {}
    stale: dict[str, Any] = {}
    champions = champion_models(client, angles, log) if documents else {}
    for doc, data in documents:
        unit_id = doc.unit_id
        units[unit_id] = register_unit(client, doc, data, log)
        missing = uncovered_angles(doc, champions)
        if missing:
            stale[unit_id] = {"angles": missing, "advice": ADVICE}
            log(
                f"{unit_model_name(unit_id)}: its calibration was made with other models than the "
                f"champions at {', '.join(missing)}°: {ADVICE}"
            )
    return {"units": dict(sorted(units.items())), "stale_units": dict(sorted(stale.items()))}
