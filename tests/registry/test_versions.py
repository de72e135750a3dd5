"""Tracking and registering, on stored predictions as the pipeline runs them: tracking runs,
champion / challenger, no double registration, rollback, an unreachable registry. Each test has
its own temp MLflow store (conftest's autouse fixture)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import typer
from mlflow import MlflowClient
from typer.testing import CliRunner

from needlecue_runtime.registry.store import ABOUT, FORMAT_TAG, RegistryUnreachable, model_name
from pipeline.config import RegisterParams, load_section
from pipeline.modelling.kinds import kind_of
from pipeline.modelling.split_predictions import predict_all
from pipeline.modelling.train import train_folder
from pipeline.registry import versions
from pipeline.stages import register
from tests.modelling.frames import make_frame

GOOD = "fnn:\n  hidden: [8]\n  max_epochs: 40\n  patience: 40\n  batch_size: 32\n"
BAD = "fnn:\n  hidden: [8]\n  max_epochs: 1\n  patience: 1\n  batch_size: 32\n"
ONLY_FNN = RegisterParams(candidates=("fnn",))


def write_data(processed: Path, angle: str = "30") -> None:
    folder = processed / angle
    folder.mkdir(parents=True)
    make_frame(4, seed=0).to_parquet(folder / "train.parquet", index=False)
    make_frame(1, seed=1, batch_id="b2").to_parquet(folder / "val.parquet", index=False)
    make_frame(1, seed=2, batch_id="b3").to_parquet(folder / "test.parquet", index=False)
    make_frame(2, seed=3, batch_id="heldout").to_parquet(folder / "external.parquet", index=False)


def train_models(tmp: Path, name: str, fnn_params: str, kinds: tuple[str, ...] = ("fnn",)) -> Path:
    """models/<kind>/30 trained by the train stage on tmp/processed/30."""
    params = tmp / f"{name}.yaml"
    params.write_text(fnn_params + "ls:\n  fit_intercept: false\n")
    models = tmp / name
    for kind in kinds:
        train(kind, tmp / "processed" / "30", models / kind / "30", params)
    return models


def train(kind: str, data: Path, out: Path, params: Path) -> None:
    train_folder(kind, load_section(kind_of(kind).params, kind, params), data, out, quiet)  # type: ignore[arg-type]


def quiet(_msg: str) -> None:
    pass


@pytest.fixture
def project(tmp_path: Path) -> Path:
    """tmp_path with processed data for 30° and an (empty) reports folder."""
    write_data(tmp_path / "processed")
    (tmp_path / "reports").mkdir()
    return tmp_path


def run_stage(
    project: Path, models: Path, params: RegisterParams = ONLY_FNN, cal_dir: Path | None = None
) -> dict:
    """The predict stage on `models`, then the register stage, as dvc.yaml runs them (with the unit
    calibrations of `cal_dir`, if given)."""
    pred = project / f"predictions-{models.name}"
    kinds = sorted(p.name for p in models.iterdir())
    predict_all(project / "processed", models, pred, kinds, ["30"], quiet)
    return versions.register_all(
        models,
        project / "processed",
        pred,
        project / "reports",
        project / "registry.json",
        params,
        quiet,
        cal_dir,
    )


def test_first_registration_tracks_every_model_and_crowns_the_best(
    project: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # given: an ls and an fnn for 30°, an empty registry, and the metric history requests counted
    models = train_models(project, "models", GOOD, kinds=("ls", "fnn"))
    histories: list[str] = []
    history = MlflowClient.get_metric_history
    monkeypatch.setattr(
        MlflowClient, "get_metric_history", lambda c, run, key: histories.append(key) or history(c, run, key)
    )
    # when
    record = run_stage(project, models, RegisterParams())
    # then: both are runs of one experiment with per-split, per-axis metrics and the tags the UI filters on
    client = MlflowClient()
    exp = client.get_experiment_by_name("needle-force")
    runs = client.search_runs([exp.experiment_id])
    assert sorted(r.data.tags["model_type"] for r in runs) == ["fnn", "ls"]
    for r in runs:
        assert {"val_nrmse_pct_fx", "test_rmse_fy", "external_nrmse_pct_mean"} <= set(r.data.metrics)
        assert r.data.tags["angle_deg"] == "30" and r.data.tags["git_commit"]
        assert r.data.tags["data_sha256"]
        # and its logged model has the run's metrics but the loss curves (logged by epoch), as the
        # UI's model page shows them ...
        (model,) = client.search_logged_models(experiment_ids=[exp.experiment_id], filter_string=
                                                f"source_run_id = '{r.info.run_id}'")  # fmt: skip
        by_epoch = {"train_loss", "val_loss"}
        assert {m.key: m.value for m in model.metrics} == {
            k: v for k, v in r.data.metrics.items() if k not in by_epoch
        }
    # ... with no request per metric for its history (one each on a tracking server: a minute for 18)
    assert histories == []
    # and: the better of the two on the external set is version 1 and champion
    entry = record["angles"]["30"]
    scores = {r.data.tags["model_type"]: r.data.metrics["external_nrmse_pct_mean"] for r in runs}
    assert entry["kind"] == min(scores, key=scores.get)
    assert (entry["action"], entry["version"], entry["aliases"]) == ("registered", 1, ["champion"])
    assert int(client.get_model_version_by_alias(model_name(30), "champion").version) == 1
    assert record["promoted"] == ["30"]
    assert json.loads((project / "registry.json").read_text()) == record
    # and: the registry's face says what things are, with no internal tag: the experiment's
    # description, and the version's, which says what its graph takes and returns
    assert exp.tags["mlflow.note.content"] == ABOUT
    assert not [t for t in exp.tags if t.startswith("needlecue.")]
    described = client.get_model_version(model_name(30), "1").description
    assert "Takes the estimator's raw readings `reading` float64" in described and "`force_n`" in described


def test_second_run_with_nothing_changed_registers_nothing(project: Path) -> None:
    # given: a registered model
    models = train_models(project, "models", GOOD)
    run_stage(project, models)
    client = MlflowClient()
    n_runs = len(client.search_runs([client.get_experiment_by_name("needle-force").experiment_id]))
    # when: the stage runs again on the same models
    record = run_stage(project, models)
    # then: no new run, no new version
    assert record["registered"] == [] and record["angles"]["30"]["action"] == "unchanged"
    assert len(client.search_runs([client.get_experiment_by_name("needle-force").experiment_id])) == n_runs
    assert [int(v.version) for v in client.search_model_versions(f"name = '{model_name(30)}'")] == [1]


def test_a_new_cue_pack_for_the_champions_model_becomes_the_champion(project: Path) -> None:
    # given: a registered champion, with the cue pack the cues stage wrote for 30°
    packs = project / "reports" / "cues" / "packs"
    packs.mkdir(parents=True)
    (packs / "30.json").write_text(json.dumps({"format": "test-pack", "min_confidence": 0.7}))
    models = train_models(project, "models", GOOD)
    run_stage(project, models)
    client = MlflowClient()
    exp_id = client.get_experiment_by_name("needle-force").experiment_id
    # when: the cues change (the same model) and the stage runs again
    (packs / "30.json").write_text(json.dumps({"format": "test-pack", "min_confidence": 0.8}))
    entry = run_stage(project, models)["angles"]["30"]
    # then: a new run and version carry the new pack, and the champion moved to it
    assert len(client.search_runs([exp_id])) == 2
    assert (entry["action"], entry["version"], entry["aliases"]) == ("registered", 2, ["champion"])
    assert "v1's own model, packed anew" in entry["reason"]
    champion = client.get_model_version_by_alias(model_name(30), "champion")
    assert champion.tags["needlecue.previous_champion"] == "1"
    # and: the stage again with that pack changes nothing
    assert run_stage(project, models)["angles"]["30"]["action"] == "unchanged"


def test_a_better_model_is_promoted_and_a_worse_one_is_only_challenger(project: Path) -> None:
    # given: a poor champion (1 epoch), then a well-trained model, then the poor one's twin again
    bad = train_models(project, "bad", BAD)
    good = train_models(project, "good", GOOD)
    first = run_stage(project, bad)["angles"]["30"]
    # when: the good one arrives
    second = run_stage(project, good)["angles"]["30"]
    # then: it beats the champion on the external set and takes the title
    assert second["external_nrmse_pct_mean"] < first["external_nrmse_pct_mean"]
    assert (second["version"], second["aliases"]) == (2, ["champion"])
    assert second["previous_champion"]["version"] == 1
    client = MlflowClient()
    assert int(client.get_model_version_by_alias(model_name(30), "champion").version) == 2
    # when: a worse model (another 1-epoch fnn, different seed) arrives
    (project / "worse.yaml").write_text(BAD.replace("batch_size: 32", "batch_size: 32\n  seed: 7"))
    train("fnn", project / "processed" / "30", project / "worse" / "fnn" / "30", project / "worse.yaml")
    third = run_stage(project, project / "worse")["angles"]["30"]
    # then: it is registered as challenger and the champion stays
    assert third["external_nrmse_pct_mean"] > second["external_nrmse_pct_mean"]
    assert (third["version"], third["aliases"]) == (3, ["challenger"])
    assert int(client.get_model_version_by_alias(model_name(30), "champion").version) == 2
    assert int(client.get_model_version_by_alias(model_name(30), "challenger").version) == 3


def test_a_champion_of_a_graph_format_clients_refuse_gives_way_and_is_never_rolled_back_to(
    project: Path,
) -> None:
    # given: a good champion registered with an older graph format (its format tag, as before
    # needlecue-deploy/4: today's clients refuse it), and a worse model arriving
    run_stage(project, train_models(project, "good", GOOD))
    client = MlflowClient()
    client.delete_model_version_tag(model_name(30), "1", FORMAT_TAG)
    (project / "worse.yaml").write_text(BAD.replace("batch_size: 32", "batch_size: 32\n  seed: 7"))
    train("fnn", project / "processed" / "30", project / "worse" / "fnn" / "30", project / "worse.yaml")
    # when: it is registered
    entry = run_stage(project, project / "worse")["angles"]["30"]
    # then: it takes the title, since the champion cannot defend it where no client runs it
    assert (entry["version"], entry["aliases"]) == (2, ["champion"])
    # and: rolling back to the old format is refused, saying why
    with pytest.raises(ValueError, match="not a needlecue-deploy/4 graph: today's clients refuse it"):
        versions.rollback(30)
    assert int(client.get_model_version_by_alias(model_name(30), "champion").version) == 2


def test_rollback_moves_the_champion_back(project: Path) -> None:
    # given: v1 (poor) replaced by v2 (good) as champion
    run_stage(project, train_models(project, "bad", BAD))
    run_stage(project, train_models(project, "good", GOOD))
    # when
    old, new = versions.rollback(30)
    # then
    assert (old, new) == (2, 1)
    assert int(MlflowClient().get_model_version_by_alias(model_name(30), "champion").version) == 1
    # and: a version that does not exist is refused, naming what exists
    with pytest.raises(ValueError, match=r"no version 9 \(versions: \[1, 2\]\)"):
        versions.rollback(30, 9)


def test_an_unreachable_registry_fails_clearly_and_changes_nothing(
    project: Path, monkeypatch: pytest.MonkeyPatch, mlflow_store: str
) -> None:
    # given: a champion in the real store, and the stage pointed at a server nobody listens on
    models = train_models(project, "models", GOOD)
    run_stage(project, models)
    (project / "registry.json").unlink()
    better = train_models(project, "good", GOOD.replace("max_epochs: 40", "max_epochs: 60"))
    monkeypatch.setenv("MLFLOW_TRACKING_URI", "http://127.0.0.1:9")
    # when: the stage runs
    with pytest.raises(RegistryUnreachable, match=r"http://127\.0\.0\.1:9.*\n.*alias is as it was"):
        run_stage(project, better)
    # then: no record was written and, back on the real store, the aliases are as they were
    assert not (project / "registry.json").exists()
    monkeypatch.setenv("MLFLOW_TRACKING_URI", mlflow_store)
    client = MlflowClient(tracking_uri=mlflow_store, registry_uri=mlflow_store)
    assert [int(v.version) for v in client.search_model_versions(f"name = '{model_name(30)}'")] == [1]
    assert int(client.get_model_version_by_alias(model_name(30), "champion").version) == 1


def test_stage_command_exits_1_with_the_reason(project: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # given: no trained models at all, so no predictions
    (project / "models").mkdir()
    (project / "predictions").mkdir()
    params = project / "params.yaml"
    params.write_text("register:\n  candidates: [fnn]\n")
    # when
    app = typer.Typer()
    app.command()(register.main)
    result = CliRunner().invoke(
        app,
        [
            str(project / "models"),
            str(project / "processed"),
            str(project / "predictions"),
            str(project / "calibration"),
            str(project / "reports"),
            str(project / "registry.json"),
            "--params",
            str(params),
        ],
    )
    # then
    assert result.exit_code == 1
    assert "no trained model folders" in result.output


def test_a_rollback_survives_the_next_run(project: Path) -> None:
    # given: v2 promoted over v1, then rolled back to v1
    bad, good = train_models(project, "bad", BAD), train_models(project, "good", GOOD)
    run_stage(project, bad)
    run_stage(project, good)
    versions.rollback(30)
    # when: the stage runs again on the same models (another angle retrained, say)
    entry = run_stage(project, good)["angles"]["30"]
    # then: v2 is left as the rollback left it, and v1 stays champion
    assert (entry["action"], entry["version"], entry["aliases"]) == ("unchanged", 2, [])
    assert int(MlflowClient().get_model_version_by_alias(model_name(30), "champion").version) == 1


def test_a_champion_whose_checkpoint_cannot_be_fetched_fails_the_stage(
    project: Path, mlflow_store: str
) -> None:
    # given: a champion whose run artifacts are gone, and a worse model arriving
    good, bad = train_models(project, "good", GOOD), train_models(project, "bad", BAD)
    run_stage(project, good)
    artifacts = Path(mlflow_store.removeprefix("sqlite:///")).parent / "mlartifacts"
    for checkpoint in artifacts.rglob("checkpoint/model.pt"):
        checkpoint.unlink()
    # when / then: the stage fails instead of waving the newcomer through, and the champion stays
    with pytest.raises(Exception, match=r"model\.pt"):
        run_stage(project, bad)
    assert int(MlflowClient().get_model_version_by_alias(model_name(30), "champion").version) == 1


def test_rollback_command(project: Path) -> None:
    # given: v2 champion over v1
    run_stage(project, train_models(project, "bad", BAD))
    run_stage(project, train_models(project, "good", GOOD))
    # when: the command rolls back to the version it replaced, then is asked for a missing version
    from pipeline.cli import app

    ok = CliRunner().invoke(app, ["rollback", "30"])
    missing = CliRunner().invoke(app, ["rollback", "30", "--to", "7"])
    # then
    assert ok.exit_code == 0 and "needle-force-30@champion: version 2 -> 1" in ok.output
    assert missing.exit_code == 1 and "no version 7" in missing.output


def test_a_version_left_without_alias_by_an_interrupted_run_is_decided_next_time(project: Path) -> None:
    # given: a run that registered version 1 and was stopped before it set an alias
    models = train_models(project, "models", GOOD)
    run_stage(project, models)
    client = MlflowClient()
    client.delete_registered_model_alias(model_name(30), "champion")
    client.delete_model_version_tag(model_name(30), "1", "needlecue.decided")
    # when: the stage runs again on the same model
    entry = run_stage(project, models)["angles"]["30"]
    # then: no second version, and the pending one gets the alias the rule gives it
    assert (entry["version"], entry["aliases"]) == (1, ["champion"])
    assert [int(v.version) for v in client.search_model_versions(f"name = '{model_name(30)}'")] == [1]
