"""End to end: `dvc repro` of the whole pipeline (simulate -> ... -> register) in a temporary copy."""

from __future__ import annotations

import json
from pathlib import Path

import pandas as pd
import pytest
import yaml
from mlflow import MlflowClient

from tests.helpers import tree_hash
from tests.projects import (
    LAB_BATCH,
    Registered,
    copy_registered,
    make_project,
    reran_stages,
    run,
    use_small_models,
)
from tests.rig.batches import copy_batch

pytestmark = pytest.mark.slow


def test_repro_builds_per_angle_datasets_then_reruns_only_what_a_change_touches(
    tiny_registered: Registered, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
):
    # Given a project on a small simulated rig (few-epoch networks: this is about the DAG), reproduced
    # through register (shared with other tests, tests/conftest.py: `needlecue repro` of every stage
    # but register, then `dvc repro`, which ran register alone), and its MLflow store
    root, params = copy_registered(tiny_registered, tmp_path, monkeypatch)
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
    # And the ledger places every simulated trial once: in a split of its angle, or calibrating
    ledger = json.loads((root / "reports" / "ledger" / "ledger.json").read_text())
    placed = {(e["batch_id"], e["trial_id"]): (e["angle"], e["use"]) for e in ledger["entries"]}
    in_splits = {
        (t["batch_id"], t["trial_id"]): (angle, split)
        for angle, entry in manifest["angles"].items()
        for split, trials in entry["splits"].items()
        for t in trials
    }
    calibrating = {
        (t["batch_id"], t["trial_id"]): (a, "calibration")
        for a, ts in manifest["calibration"].items()
        for t in ts
    }
    assert placed == in_splits | calibrating and len(placed) == len(ledger["entries"])
    assert ledger["counts"]["set_aside"] == 0
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
    assert changed_stages(root) == set()
    # When only the LSTM's settings change
    params["lstm"]["hidden"] = params["lstm"]["hidden"] + 1
    (root / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    # Then only the LSTM stages are out of date (the stages that read every model follow once they rerun:
    # calibrate, because a calibration belongs to the models it was made with, and the ledger, which
    # reads the calibrations)
    assert changed_stages(root) == {"choose@lstm", "train@15-lstm", "train@45-lstm"}
    out = run(root, "dvc", "repro")
    assert reran_stages(out) == {
        "choose@lstm",
        "train@15-lstm",
        "train@45-lstm",
        "calibrate",
        "ledger",
        "predict",
        "cues",
        "evaluate",
        "report",
        "register",
    }, out


def _recording(share: Path, name: str, *, angle: int, variant: int) -> Path:
    """The hand-written lab batch as batch `name` in `share`, every trial at `angle`°, each estimator
    stream's first voltage with the digit `variant` appended (another recording for each `variant`, not
    a copy, which split would set aside: a copy has the same samples, whatever its timestamps)."""
    batch = copy_batch(LAB_BATCH, share, name)
    trials = pd.read_csv(batch / "trials.csv")
    trials["angle_deg"] = angle
    trials.to_csv(batch / "trials.csv", index=False)
    for fsr in batch.glob("*.fsr.csv"):
        rows = fsr.read_text().splitlines()
        cells = rows[1].split(",")
        cells[1] += str(variant)
        rows[1] = ",".join(cells)
        fsr.write_text("\n".join(rows) + "\n")
    return batch


def test_a_single_angle_lab_follows_the_readme_with_params_only(tmp_path):
    # Given a lab with one angle, as docs/lab-data.md says: hand-written rig-log/1 batches
    # (4 channels, volts, mN) in a folder of its own, the simulator off, `train.angles: [30]`,
    # its held-out batch named in `split.external_batches`
    root = make_project(tmp_path / "proj", {"enabled": False})
    share = tmp_path / "lab-share"
    _recording(share, "lab-bench-a", angle=30, variant=1)
    _recording(share, "lab-heldout-a", angle=30, variant=2)
    # (few-epoch networks of every kind: the test is of the data's way through, not of accuracy)
    params = use_small_models(root, kinds=("ls", "fnn", "lstm"))
    params["data"]["raw_dir"] = str(share)
    params["train"]["angles"] = [30]
    params["split"]["external_batches"] = ["lab-heldout-*"]
    (root / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    before = tree_hash(share)
    # When the pipeline runs
    run(root, "dvc", "repro")
    # Then its one angle comes out with its own channel names, in volts and newtons
    manifest = json.loads((root / "data" / "processed" / "manifest.json").read_text())
    assert sorted(manifest["angles"]) == ["30"]
    assert manifest["angles"]["30"]["channels"] == ["left", "right", "top", "bottom"]
    external = pd.read_parquet(root / "data" / "processed" / "30" / "external.parquet")
    assert set(external.batch_id) == {"lab-heldout-a"}
    frames = [pd.read_parquet(p) for p in (root / "data" / "processed" / "30").glob("*.parquet")]
    data = pd.concat([f for f in frames if len(f)])
    assert data.fx.abs().max() < 5.0  # newtons, not millinewtons
    # And its champion is registered, in the store MLFLOW_TRACKING_URI names
    champion = MlflowClient().get_model_version_by_alias("needle-force-30", "champion")
    assert int(champion.version) == 1
    # And the lab's folder is exactly as it was
    assert tree_hash(share) == before
    # And the ledger has all six trials used
    ledger = json.loads((root / "reports" / "ledger" / "ledger.json").read_text())
    assert ledger["counts"]["trials"] == ledger["counts"]["used"] == 6, ledger["counts"]
    # (A second batch, then: only it is parsed, the others reused from the ingest cache, every new trial
    # placed. tests/rig/test_ingest.py checks that on this lab batch, and tests/test_retrain.py through
    # `dvc repro` on a project, the ledger's report included.)


def changed_stages(root: Path) -> set[str]:
    """Stage names `dvc status` reports as changed."""
    out = run(root, "dvc", "status", "--json")
    return set(json.loads(out[out.index("{") :]))
