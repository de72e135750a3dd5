"""Estimator units in the registry: each calibration document a version of `needle-unit-<unit_id>`
with `@current`, registered once, checked against the current champions; and the register stage's
registry.json entries. Each test has its own temp MLflow store (conftest's autouse fixture)."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import pandas as pd
import pytest
from mlflow import MlflowClient

from needlecue_runtime.registry import store
from needlecue_runtime.unit_calibration import FILE, read_unit, write_unit
from pipeline.calibration.unit import calibrate_unit
from pipeline.config import CalibrateParams, RegisterParams
from pipeline.modelling.fit import fit
from pipeline.modelling.predictor import Predictor, load_predictor
from pipeline.registry import calibrations
from tests.client.builders import TINY, cue_trials, register
from tests.registry.test_versions import GOOD, quiet, run_stage, train_models, write_data

UNIT = "est-901"
QUICK = CalibrateParams(min_trial_s=1.0, max_iter=20)


def calibration_rows(angle: float = 30.0, unit: str = UNIT) -> pd.DataFrame:
    """One short calibration trial of `unit` at `angle`, as the split stage sets them apart."""
    rows = cue_trials(angle, 1, f"cal-{unit}", seed=11)
    return rows.assign(unit_id=unit, fx=1.2 * rows["fx"], fz=0.8 * rows["fz"])


def document(predictor: Predictor, cal_dir: Path, unit: str = UNIT) -> Path:
    """The unit's calibration through `predictor`, written as the calibrate stage writes it."""
    doc = calibrate_unit(
        unit, calibration_rows(unit=unit), {predictor.kind: {"30": predictor}}, ["30"], QUICK
    )
    return write_unit(doc, cal_dir)


@pytest.fixture
def champion(tmp_path: Path, mlflow_store: str) -> Predictor:
    """A tiny LS needle-force-30@champion in this test's store."""
    checkpoint = fit("ls", TINY["ls"], cue_trials(30, 2)).checkpoint
    register(mlflow_store, tmp_path, checkpoint, with_checkpoint=True)
    return Predictor(checkpoint)


def register_dir(cal_dir: Path) -> dict:
    return calibrations.register_units(store.connect(), calibrations.load_documents(cal_dir), None, quiet)


def test_a_calibration_becomes_a_unit_version_with_the_current_alias(
    champion: Predictor, tmp_path: Path, mlflow_store: str
) -> None:
    # given: a unit's calibration document made through the champion
    path = document(champion, tmp_path / "calibration")
    # when: the registry takes every document of the folder
    record = register_dir(tmp_path / "calibration")
    # then: version 1 of needle-unit-<unit>, @current, not stale
    assert record == {
        "units": {UNIT: {"version": 1, "action": "registered", "aliases": ["current"]}},
        "stale_units": {},
    }
    client = MlflowClient()
    name = store.unit_model_name(UNIT)
    current = client.get_model_version_by_alias(name, store.UNIT_ALIAS)
    sha = hashlib.sha256(path.read_bytes()).hexdigest()
    assert (int(current.version), current.tags[calibrations.SHA_TAG]) == (1, sha)
    # and: one run of needle-units with the document's params, losses per kind, tags and the document
    run = client.get_run(current.run_id)
    assert client.get_experiment(run.info.experiment_id).name == "needle-units"
    doc = read_unit(path)
    assert run.data.params["ridge"] == str(doc.params["ridge"])
    assert run.data.metrics["ls_loss_before"] == pytest.approx(doc.transforms["ls"].loss_before)
    assert run.data.metrics["ls_loss_after"] < run.data.metrics["ls_loss_before"]
    assert {k: run.data.tags[k] for k in ("unit_id", "batches", "angles_used", "angles_missing")} == {
        "unit_id": UNIT,
        "batches": f"cal-{UNIT}",
        "angles_used": "30",
        "angles_missing": "",
    }
    assert run.data.tags[calibrations.SHA_TAG] == sha
    # and: the version is the run's plain artifact folder, which downloads as calibration.json
    assert current.source == f"{run.info.artifact_uri}/calibration"
    import mlflow

    got = Path(mlflow.artifacts.download_artifacts(f"models:/{name}@current", dst_path=str(tmp_path / "dl")))
    assert (got / FILE).read_bytes() == path.read_bytes()


def test_the_same_document_is_registered_once_and_current_never_moves_back(
    champion: Predictor, tmp_path: Path
) -> None:
    # given: a registered calibration
    cal = tmp_path / "calibration"
    first = document(champion, cal).read_bytes()
    register_dir(cal)
    client = MlflowClient()
    name = store.unit_model_name(UNIT)
    # when: registered again, unchanged
    again = register_dir(cal)
    # then: nothing new: one version, one run
    assert again["units"][UNIT] == {"version": 1, "action": "unchanged", "aliases": ["current"]}
    assert len(client.search_model_versions(f"name = '{name}'")) == 1
    runs = client.search_runs([client.get_experiment_by_name("needle-units").experiment_id])
    assert len(runs) == 1

    # when: a new calibration (other settings), then the first document again
    doc = json.loads((cal / f"{UNIT}.json").read_text())
    doc["params"]["ridge"] = 0.5
    write_unit(doc, cal)
    newer = register_dir(cal)["units"][UNIT]
    (cal / f"{UNIT}.json").write_bytes(first)
    older = register_dir(cal)["units"][UNIT]
    # then: the new one is version 2 @current, and the old one's return moves nothing
    assert (newer["version"], newer["action"]) == (2, "registered")
    assert (older["version"], older["action"], older["aliases"]) == (1, "unchanged", [])
    assert int(client.get_model_version_by_alias(name, "current").version) == 2

    # when: a registration was interrupted before its alias (the alias is gone)
    client.delete_registered_model_alias(name, "current")
    resumed = register_dir(cal)["units"][UNIT]
    # then: the alias is set, and still no new version
    assert (resumed["version"], resumed["action"]) == (1, "alias_set")
    assert int(client.get_model_version_by_alias(name, "current").version) == 1
    assert len(client.search_model_versions(f"name = '{name}'")) == 2


def test_a_calibration_made_with_other_models_than_the_champions_is_stale_not_an_error(
    champion: Predictor, tmp_path: Path, mlflow_store: str
) -> None:
    # given: a calibration made through v1, and v2 (another model) now champion
    cal = tmp_path / "calibration"
    document(champion, cal)
    doubled = cue_trials(30, 2).pipe(lambda f: f.assign(fx=2 * f["fx"]))
    register(mlflow_store, tmp_path, fit("ls", TINY["ls"], doubled).checkpoint)
    # when: the registry takes it
    record = register_dir(cal)
    # then: registered all the same, and reported stale with the advice
    assert record["units"][UNIT]["action"] == "registered"
    assert record["stale_units"] == {UNIT: {"angles": ["30"], "advice": "run needlecue calibrate"}}


def test_a_champion_without_a_readable_mlmodel_is_left_out_and_the_others_are_read(
    champion: Predictor, tmp_path: Path, mlflow_store: str
) -> None:
    # given: beside the LS champion at 30°, a champion at 5° registered from a run that logged nothing
    # (as another tool might), and one at 45° whose MLmodel was lost from its logged model
    client = store.connect(write=True)
    run = client.create_run(store.experiment_id(client, store.EXPERIMENT))
    store.create_registered_model(client, "needle-force-5", "no model behind it")
    empty = client.create_model_version("needle-force-5", f"runs:/{run.info.run_id}/model", run.info.run_id)
    client.set_registered_model_alias("needle-force-5", store.CHAMPION, empty.version)
    register(mlflow_store, tmp_path, fit("ls", TINY["ls"], cue_trials(45, 2)).checkpoint, angle=45)
    location = client.get_model_version_download_uri("needle-force-45", "1")
    Path(location.removeprefix("file://"), "MLmodel").unlink()
    said: list[str] = []
    # when: the champions are read, and their checkpoints loaded, as `needlecue calibrate` does
    champions = calibrations.champion_models(client, log=said.append)
    models = calibrations.champion_predictors(client, champions, said.append)
    # then: 30° is read and loaded; 5° and 45° are left out, each saying which version and why
    assert list(champions) == ["30"] and list(models["ls"]) == ["30"]
    assert {line.split(": no MLmodel among its files")[0] for line in said} == {
        "needle-force-45 v1 (@champion)",
        f"needle-force-5 v{empty.version} (@champion)",
    }
    assert all(line.endswith(": left out") for line in said)


def test_a_registry_that_fails_while_the_champions_are_read_is_an_error_not_a_left_out_angle(
    champion: Predictor, monkeypatch: pytest.MonkeyPatch
) -> None:
    # given: the artifact store failing (a server error) when a champion's files are listed
    import mlflow
    from mlflow.exceptions import MlflowException

    def fails(**_kwargs: object) -> None:
        raise MlflowException("API request failed with error code 503")

    monkeypatch.setattr(mlflow.artifacts, "list_artifacts", fails)
    # when / then: the failure is raised, not taken for a champion without a model
    with pytest.raises(MlflowException, match="503"):
        calibrations.champion_models(store.connect(), log=lambda _m: None)


def test_the_register_stage_registers_the_units_beside_the_champions(tmp_path: Path) -> None:
    # given: an LS model of 30° trained and predicted as the pipeline does, a unit calibrated through
    # it, and a second unit calibrated through a model that was never registered
    project = tmp_path
    write_data(project / "processed")
    (project / "reports").mkdir()
    models = train_models(project, "models", GOOD, kinds=("ls",))
    cal = project / "calibration"
    document(load_predictor(models / "ls" / "30"), cal)
    other = fit("ls", TINY["ls"], cue_trials(30, 2)).checkpoint
    document(Predictor(other), cal, unit="est-902")
    # when: the register stage runs with the calibration folder
    record = run_stage(project, models, RegisterParams(candidates=("ls",)), cal_dir=cal)
    # then: registry.json has both units @current, the second one stale; the champion as before
    assert record["angles"]["30"]["aliases"] == ["champion"]
    assert {u: (e["version"], e["action"]) for u, e in record["units"].items()} == {
        UNIT: (1, "registered"),
        "est-902": (1, "registered"),
    }
    assert record["stale_units"] == {"est-902": {"angles": ["30"], "advice": "run needlecue calibrate"}}
    assert json.loads((project / "registry.json").read_text()) == record
    # when: it runs again, nothing changed
    again = run_stage(project, models, RegisterParams(candidates=("ls",)), cal_dir=cal)
    # then: nothing is registered twice
    assert {u: e["action"] for u, e in again["units"].items()} == {UNIT: "unchanged", "est-902": "unchanged"}


def test_a_broken_calibration_document_fails_the_stage_before_anything_is_registered(tmp_path: Path) -> None:
    # given: a calibration folder holding a file that is not a calibration document
    write_data(tmp_path / "processed")
    (tmp_path / "reports").mkdir()
    models = train_models(tmp_path, "models", GOOD, kinds=("ls",))
    (tmp_path / "calibration").mkdir()
    (tmp_path / "calibration" / "est-9.json").write_text('{"format": "other"}')
    # when / then: a ValueError naming the file, and no model registered
    with pytest.raises(ValueError, match=r"est-9\.json: not a needlecue-unit/4 document"):
        run_stage(tmp_path, models, RegisterParams(candidates=("ls",)), cal_dir=tmp_path / "calibration")
    assert MlflowClient().search_registered_models() == []


def test_unit_names() -> None:
    assert store.unit_model_name("est-sim-101") == "needle-unit-est-sim-101"
    with pytest.raises(ValueError, match="not an estimator unit id"):
        store.unit_model_name("bad id'")
