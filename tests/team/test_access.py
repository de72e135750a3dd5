"""Roles on the team's MLflow server: anonymous refused, a simulator reads only, the lab writes."""

from __future__ import annotations

import pytest
import requests

from needlecue_runtime.registry import store
from pipeline.team import access

# the real servers, on one xdist worker (their tests share one stack), in file order
pytestmark = [pytest.mark.team, pytest.mark.xdist_group("team")]
SEARCH = "/api/2.0/mlflow/registered-models/search"


def _call(team, role, method, path, body=None):
    auth = None if role is None else (role, team.settings["passwords"][role])
    return requests.request(method, team.tracking_uri + path, json=body, auth=auth, timeout=20)


def test_anonymous_and_wrong_passwords_are_refused(team):
    # Given the running stack; when nobody signs in, or with a wrong password
    anonymous = _call(team, None, "GET", SEARCH)
    wrong = requests.get(team.tracking_uri + SEARCH, auth=("lab", "not-the-password"), timeout=20)
    # Then both are refused before anything is read
    assert anonymous.status_code == 401
    assert wrong.status_code == 401


def test_a_simulator_reads_but_cannot_create_a_run_move_an_alias_or_create_a_model(team, as_role):
    # Given an experiment, a model and its version made by the lab
    as_role("lab")
    lab = store.connect(write=True)
    exp = store.experiment_id(lab, "access-check", "made by the access test")
    run = lab.create_run(exp)
    store.create_registered_model(lab, "needle-force-5", "access test")
    version = lab.create_model_version("needle-force-5", f"runs:/{run.info.run_id}/model", run.info.run_id)
    lab.set_registered_model_alias("needle-force-5", store.CHAMPION, version.version)
    # When a simulator signs in
    as_role("simulator")
    # Then it can read the champion ...
    sim = store.connect(must_exist=True)
    assert store.alias_version(sim, "needle-force-5", store.CHAMPION).version == version.version
    # ... and is refused every write, each with 403 from the server
    assert (
        _call(team, "simulator", "POST", "/api/2.0/mlflow/runs/create", {"experiment_id": exp}).status_code
        == 403
    )
    alias = {"name": "needle-force-5", "alias": store.CHAMPION, "version": version.version}
    assert (
        _call(team, "simulator", "POST", "/api/2.0/mlflow/registered-models/alias", alias).status_code == 403
    )
    new_model = {"name": "needle-force-6"}
    assert (
        _call(team, "simulator", "POST", "/api/2.0/mlflow/registered-models/create", new_model).status_code
        == 403
    )
    new_exp = {"name": "simulators-own"}
    assert _call(team, "simulator", "POST", "/api/2.0/mlflow/experiments/create", new_exp).status_code == 403
    # ... and our own write check says so before a writer starts
    with pytest.raises(store.ReadOnlyStore, match="read-only credentials"):
        store.connect(write=True)


def test_a_new_user_gets_exactly_its_role(team):
    # Given a second simulator user made by the admin
    password = access.add_user(team, "sim-bay-2", "simulator")
    auth = ("sim-bay-2", password)
    # When it reads, and when it tries to create a registered model
    read = requests.get(team.tracking_uri + SEARCH, auth=auth, timeout=20)
    write = requests.post(
        team.tracking_uri + "/api/2.0/mlflow/registered-models/create",
        json={"name": "x-by-bay-2"},
        auth=auth,
        timeout=20,
    )
    # Then it reads and is refused the write
    assert read.status_code == 200
    assert write.status_code == 403
    with pytest.raises(ValueError, match="admin is MLflow's own"):
        access.add_user(team, "root2", "admin")
