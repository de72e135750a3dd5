"""End to end: `dvc repro` of the whole pipeline (simulate -> ... -> register) in a temporary copy."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest
import yaml
from mlflow import MlflowClient

from tests.helpers import tree_hash

REPO = Path(__file__).resolve().parents[1]
LAB_BATCH = REPO / "tests" / "fixtures" / "rig-log" / "lab-bench-a"
SMALL_SIM = {
    "angles_deg": [15, 45],
    "train_batches": 1,
    "trials_per_angle": 4,
    "heldout_trials_per_angle": 2,
}

pytestmark = pytest.mark.slow


def make_project(root: Path, simulate: dict) -> Path:
    """A throw-away copy of the project (code, dvc.yaml, params.yaml) with its own DVC repo."""
    root.mkdir()
    for name in ("dvc.yaml", ".dvcignore"):
        if (REPO / name).exists():
            shutil.copy(REPO / name, root / name)
    shutil.copytree(REPO / "pipeline", root / "pipeline", ignore=shutil.ignore_patterns("__pycache__"))
    params = yaml.safe_load((REPO / "params.yaml").read_text())
    params["simulate"].update(simulate)
    if "angles_deg" in simulate:  # train only the angles the small rig records
        params["train"]["angles"] = simulate["angles_deg"]
    if not params["simulate"].get("enabled", True):
        params["train"]["angles"] = [30, 45]  # the hand-written lab batch's angles
    (root / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    (root / "data" / "raw").mkdir(parents=True)
    run(root, "dvc", "init", "--no-scm", "-q")
    run(root, "dvc", "config", "core.analytics", "false")
    return root


def run(root: Path, *cmd: str) -> str:
    """Run a command of the venv (dvc, python) in the copy; fail with its output if it fails."""
    env = dict(os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}")
    done = subprocess.run(cmd, cwd=root, env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, f"{' '.join(cmd)} failed:\n{done.stdout}\n{done.stderr}"
    return done.stdout + done.stderr


def test_repro_builds_per_angle_datasets_then_does_nothing(tmp_path):
    # Given a fresh project on a small simulated rig
    root = make_project(tmp_path / "proj", SMALL_SIM)
    # When the pipeline runs
    run(root, "dvc", "repro")
    # Then every angle has its four splits, and no trial is in two of them
    manifest = json.loads((root / "data" / "processed" / "manifest.json").read_text())
    assert sorted(manifest["angles"]) == ["15", "45"]
    for angle in ("15", "45"):
        seen: set[tuple[str, str]] = set()
        for split in ("train", "val", "test", "external"):
            frame = pd.read_parquet(root / "data" / "processed" / angle / f"{split}.parquet")
            trials = set(zip(frame.batch_id, frame.trial_id, strict=True))
            assert trials, f"{angle}/{split} is empty"
            assert not trials & seen
            seen |= trials
            assert (frame.batch_id.str.contains("heldout")).all() == (split == "external")
        assert {"fsr1", "fsr2", "fsr3", "fx", "fy", "fz", "phase", "t_s"} <= set(frame.columns)
    assert (root / "reports" / "ingest" / "quarantine.json").exists()
    assert json.loads((root / "reports" / "ingest" / "quarantine.json").read_text()) == []
    # And every angle's best model is registered and champion, in the store MLFLOW_TRACKING_URI names
    registry = json.loads((root / "reports" / "registry.json").read_text())
    assert registry["registered"] == registry["promoted"] == ["15", "45"]
    client = MlflowClient()
    for angle in ("15", "45"):
        champion = client.get_model_version_by_alias(f"needle-force-{angle}", "champion")
        assert int(champion.version) == registry["angles"][angle]["version"] == 1
    runs = client.search_runs([client.get_experiment_by_name("needle-force").experiment_id])
    assert len(runs) == 6  # 2 angles x ls, fnn, lstm
    # And a second run has nothing to do and registers nothing
    again = run(root, "dvc", "repro")
    assert "Data and pipelines are up to date" in again, again
    for angle in ("15", "45"):
        assert len(client.search_model_versions(f"name = 'needle-force-{angle}'")) == 1


def test_a_lab_folder_goes_through_with_params_only(tmp_path):
    # Given a hand-written rig-log/1 batch (4 channels, volts, mN) and the simulator off
    root = make_project(tmp_path / "proj", {"enabled": False})
    raw = root / "data" / "raw"
    shutil.copytree(LAB_BATCH, raw / LAB_BATCH.name)
    before = tree_hash(raw)
    # When the pipeline runs
    run(root, "dvc", "repro")
    # Then its angles come out with its own channel names, in volts and newtons
    manifest = json.loads((root / "data" / "processed" / "manifest.json").read_text())
    assert sorted(manifest["angles"]) == ["30", "45"]
    assert manifest["angles"]["30"]["channels"] == ["left", "right", "top", "bottom"]
    frames = [pd.read_parquet(p) for p in (root / "data" / "processed" / "30").glob("*.parquet")]
    data = pd.concat([f for f in frames if len(f)])
    assert data.fx.abs().max() < 5.0  # newtons, not millinewtons
    # And the raw folder is exactly as it was
    assert tree_hash(raw) == before

    # When a second batch arrives
    shutil.copytree(LAB_BATCH, raw / "lab-bench-b")
    text = (raw / "lab-bench-b" / "batch.yaml").read_text().replace("lab-bench-a", "lab-bench-b")
    (raw / "lab-bench-b" / "batch.yaml").write_text(text)
    out = run(root, "dvc", "repro")
    # Then only the new batch is parsed; the first one is reused from the ingest cache
    assert "lab-bench-b: parsed" in out, out
    assert "lab-bench-a: reused" in out, out


TINY_MODELS = {
    "fnn": {"max_epochs": 3, "patience": 2},
    "lstm": {"max_epochs": 2, "patience": 1},
}


def changed_stages(root: Path) -> set[str]:
    """Stage names `dvc status` reports as changed."""
    out = run(root, "dvc", "status", "--json")
    return set(json.loads(out[out.index("{") :]))


def make_tiny_project(root: Path) -> tuple[Path, dict]:
    """make_project on the small rig with few-epoch networks (for tests of the DAG, not of accuracy);
    returns the folder and its params."""
    root = make_project(root, SMALL_SIM)
    params = yaml.safe_load((root / "params.yaml").read_text())
    for model, update in TINY_MODELS.items():
        params[model].update(update)
    (root / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    return root, params


def test_changing_one_models_params_reruns_only_that_model(tmp_path):
    # Given a small project trained end to end
    root, params = make_tiny_project(tmp_path / "proj")
    run(root, "dvc", "repro")
    assert (root / "reports" / "metrics.json").is_file()
    assert changed_stages(root) == set()
    # When only the LSTM's settings change
    params["lstm"]["hidden"] = params["lstm"]["hidden"] + 1
    (root / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    # Then only the LSTM stages are out of date (the stages that read every model follow once they rerun)
    assert changed_stages(root) == {"train@15-lstm", "train@45-lstm"}
    out = run(root, "dvc", "repro")
    reran = {line.split("'")[1] for line in out.splitlines() if line.startswith("Running stage")}
    assert reran == {"train@15-lstm", "train@45-lstm", "predict", "cues", "evaluate", "report", "register"}, (
        out
    )
