"""End to end, a lab whose reference is a one-axis load cell (issue 56): the built-in simulator
writes `t_s,fz` reference files (`simulate.reference_axes: [fz]`), and `dvc repro` takes them through
register. Every stage estimates fz alone: no zero or NaN stands in for fx or fy anywhere, and the
registered champion gives one force per sample in the Python client and in the Node client."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from needlecue_client import ForceClient
from pipeline.metrics.document import read_evaluation
from pipeline.modelling.prediction_store import Predictions
from tests.deploy.test_node import node_ready, publish_to, replay_in_node
from tests.projects import SMALL_SIM, first_external_trial, make_project, new_store, run, use_small_models

# one worker for the module: the project it builds (about 45 s) is a module fixture, and xdist's loadgroup
# would build it once on each worker its tests land on
pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("one-axis")]

NEW = SMALL_SIM["new_units"][0]  # the new unit, with its calibration batch
SIM = {**SMALL_SIM, "reference_axes": ["fz"]}


@pytest.fixture(scope="module")
def fz_project(empty_store: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The small rig with a one-axis reference, reproduced through register into its own MLflow store."""
    root = make_project(tmp_path_factory.mktemp("fz") / "proj", SIM)
    use_small_models(root)
    run(root, "dvc", "repro", env={"MLFLOW_TRACKING_URI": new_store(empty_store, root)})
    return root


def test_a_one_axis_reference_is_estimated_on_that_axis_through_every_stage(fz_project: Path) -> None:
    # given: the project reproduced on `t_s,fz` reference files
    root = fz_project
    raw = next((root / "data" / "simulated").glob("*/*.ref.csv"))
    assert raw.read_text().splitlines()[0] == "t_s,fz"
    # then: the split files hold fz and no other force; every model estimates fz alone
    for angle in ("15", "45"):
        for split in ("train", "external"):
            columns = pd.read_parquet(root / "data" / "processed" / angle / f"{split}.parquet").columns
            assert "fz" in columns and not {"fx", "fy"} & set(columns)
    predictions = Predictions(root / "data" / "predictions")
    assert {predictions.axes(k, a) for k, a in predictions.models()} == {("fz",)}
    # and: evaluation.json scores fz only; the report's tables have an Fz column and no Fx or Fy
    evaluation = read_evaluation(root / "reports" / "evaluation.json")
    scored = {axis for by_angle in evaluation.within_angle.values() for s in by_angle.values() for axis in s}
    assert scored == {"fz"}
    assert all(set(m.within_angle) == {"fz"} for m in evaluation.mean.values())
    report = (root / "reports" / "report.md").read_text()
    tables = [line for line in report.splitlines() if line.startswith("|")]
    assert "| Fz |" in report and not [t for t in tables if "Fx" in t or "Fy" in t]
    metrics = json.loads((root / "reports" / "metrics.json").read_text())
    assert "fx" not in json.dumps(metrics) and "fy" not in json.dumps(metrics)
    # and: every trial is used (none set aside for its missing axes), the new unit calibrated on fz
    ledger = json.loads((root / "reports" / "ledger" / "ledger.json").read_text())
    assert ledger["counts"]["set_aside"] == 0 and ledger["counts"]["trials"] > 0
    calibration = json.loads((root / "data" / "calibration" / f"{NEW}.json").read_text())
    assert calibration["trials"] and not calibration.get("set_aside")


def test_the_registered_one_axis_champion_gives_one_force_per_sample_in_python_and_node(
    fz_project: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # given: the registered 15° champion and a held-out trial of the calibrated new unit
    root = fz_project
    uri = f"sqlite:///{root / 'mlflow.db'}"
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    monkeypatch.chdir(root)
    client = ForceClient.from_registry(15, unit_id=NEW, cache_dir=tmp_path / "cache", poll_s=None)
    rows = first_external_trial(root, "15", NEW)
    volts, times = rows[list(client.channels)].to_numpy(), rows.t_s.to_numpy()
    # when: the Python client steps through it
    client.reset()
    forces = np.asarray([client.step(v, t).force_n for v, t in zip(volts, times, strict=True)])
    # then: one force per sample, fz, the one the pipeline scored for that unit
    expected = Predictions(root / "data" / "predictions").get(client.kind, "15", "15", "external")
    assert client.targets == ("fz",) and client.calibrated
    assert forces.shape == (len(rows), 1)
    np.testing.assert_allclose(forces, expected[rows.index.to_numpy()], atol=1e-4)
    if not node_ready():
        pytest.skip("needs node and `make setup-node` (deploy/node)")
    # when: the Node client replays the same trial from the published champion
    key = publish_to(tmp_path / "bucket", uri, "15", NEW)
    got = replay_in_node(tmp_path / "bucket", key, rows, tmp_path, NEW, "15")
    # then: it read fz from the description and gives Python's force, one value per sample
    assert got["targets"] == ["fz"] and got["calibrated"]
    np.testing.assert_allclose(np.asarray(got["force_n"]), forces, rtol=0, atol=1e-5)


def test_params_ask_for_axes_the_simulator_knows(tmp_path: Path) -> None:
    # given: a params file whose simulate.reference_axes names no force axis
    params = yaml.safe_load((Path(__file__).resolve().parents[1] / "params.yaml").read_text())
    params["simulate"]["reference_axes"] = ["fw"]
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump(params))
    # when / then: loading the section fails, naming the key
    from pipeline.config import SimulateParams, load_section

    with pytest.raises(ValueError, match="reference_axes"):
        load_section(SimulateParams, "simulate", path)
