"""`needlecue retrain`: the lock, pending batches, the report, and end to end on a small project."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from mlflow import MlflowClient
from typer.testing import CliRunner

from pipeline import retrain
from pipeline.cli import app
from pipeline.config import IngestParams
from pipeline.execution.dvc_api import Busy
from tests.helpers import tree_hash
from tests.metrics.documents import evaluation
from tests.projects import LAB_BATCH, Registered, copy_registered


def test_lock_refuses_a_second_holder_and_names_the_first(tmp_path: Path) -> None:
    # given: one holder of the lock
    path = tmp_path / "lock"
    busy = pytest.raises(Busy, match=rf"another retrain is running \(pid {os.getpid()}, started")
    # when: a second one tries (a second file descriptor, as another process would have)
    with retrain.lock(path), busy, retrain.lock(path):
        pass
    # then: once released it can be taken again
    with retrain.lock(path):
        pass


def test_pending_batches_are_the_new_and_the_changed(tmp_path: Path) -> None:
    # given: a raw folder with one batch the last ingest has seen, and an ingest record of it
    from pipeline.rig.ingest import ingest_batches

    raw, ingested = tmp_path / "raw", tmp_path / "ingested"
    shutil.copytree(LAB_BATCH, raw / "lab-bench-a")
    params = IngestParams()
    ingest_batches([raw], ingested, params, log=lambda _m: None)
    assert retrain.pending_batches(raw, ingested, params) == []
    # when: a batch arrives and the known one changes
    shutil.copytree(LAB_BATCH, raw / "lab-bench-b")
    with (raw / "lab-bench-a" / "trials.csv").open("a") as f:
        f.write("\n")
    # then
    pending = retrain.pending_batches(raw, ingested, params)
    assert [(p.batch_id, p.status) for p in pending] == [("lab-bench-a", "changed"), ("lab-bench-b", "new")]


def test_the_batches_of_a_run_that_did_not_finish_are_the_next_runs_too(tmp_path: Path) -> None:
    # given: a run that took three batches and did not finish: one is still pending (changed again),
    # one was ingested (no longer pending), one was deleted since
    for name in ("cast-1", "cast-2"):
        (tmp_path / "data" / "raw" / name).mkdir(parents=True)
    taken = [
        {"batch_id": b, "path": str(tmp_path / "data" / "raw" / b), "status": "new"}
        for b in ("cast-1", "cast-2", "gone")
    ]
    (tmp_path / retrain.UNFINISHED).parent.mkdir(parents=True)
    (tmp_path / retrain.UNFINISHED).write_text(json.dumps(taken))
    pending = [retrain.Pending("cast-1", str(tmp_path / "data" / "raw" / "cast-1"), "changed")]
    # when: the next run looks for what it has to report
    merged = retrain.with_unfinished(pending, tmp_path)
    # then: the pending batches, then the ingested one the killed run took; not the one deleted
    assert [(p.batch_id, p.status) for p in merged] == [("cast-1", "changed"), ("cast-2", "new")]
    # and a file it cannot read changes nothing
    (tmp_path / retrain.UNFINISHED).write_text("[{")
    assert retrain.with_unfinished(pending, tmp_path) == pending


def _nrmse(value: float) -> dict:
    return {"rmse": None, "nrmse_pct": value}


def test_summary_lists_retrained_angles_metrics_and_promotions() -> None:
    # given: a run that retrained 15° and registered a better model there
    pending = [
        retrain.Pending("cast-7", "data/raw/cast-7", "new"),
        retrain.Pending("bad", "data/raw/bad", "new"),
    ]
    ran = ["ingest", "resample", "split", "train@15-ls", "train@15-fnn", "cues", "evaluate", "register"]
    before = evaluation(within_angle={"fnn": {"15": {"fx": _nrmse(6.0), "fy": _nrmse(4.0)}}})
    after = evaluation(within_angle={"fnn": {"15": {"fx": _nrmse(5.0), "fy": _nrmse(3.0)}}})
    entry = {
        "model": "needle-force-15",
        "version": 2,
        "kind": "fnn",
        "aliases": ["champion"],
        "action": "registered",
    }
    registry = {"angles": {"15": entry, "45": {**entry, "action": "unchanged"}}}
    # and a ledger: cast-7's t1 trained on, its t2 set aside by split, `bad` set aside whole by ingest
    used = {"outcome": "used", "stage": "split", "angle": "15", "use": "train"}
    channels = {
        "file": "data/raw/cast-7/t2.*",
        "reason": "channels ['a0'] differ from the channels ['a0', 'a1']",
    }
    no_yaml = {"file": "data/raw/bad", "reason": "no batch.yaml"}
    ledger = {
        "entries": [
            {
                "batch_id": "bad",
                "source": "data/raw/bad",
                "outcome": "set aside",
                "stage": "ingest",
                "where": [no_yaml],
            },
            {"batch_id": "cast-7", "trial_id": "t1", "source": "data/raw/cast-7", **used},
            {
                "batch_id": "cast-7",
                "trial_id": "t2",
                "source": "data/raw/cast-7",
                "outcome": "set aside",
                "stage": "split",
                "where": [channels],
            },
            {"batch_id": "old", "trial_id": "t1", "source": "data/raw/old", **used},
        ]
    }
    # when
    report = retrain.summarise(pending, ran, before, after, registry, ledger)
    # then
    assert report["angles_retrained"] == ["15"]
    assert report["metrics"] == {"15": {"before": {"fnn": 5.0}, "after": {"fnn": 4.0}}}
    assert report["batches_set_aside"] == ["bad"]
    assert [(e["batch_id"], e["trial_id"], e["stage"]) for e in report["trials_set_aside"]] == [
        ("cast-7", "t2", "split")
    ]
    assert list(report["registered"]) == ["15"] and report["promoted"] == ["15"]
    # and a trial set aside by split, after ingest passed it, makes the retrain exit 3
    assert retrain.outcome(0, report) == (retrain.EXIT_SET_ASIDE, "retrained, some new data set aside")
    text = retrain.render(
        {**report, "started": "2026-11-23T12:00:00Z", "outcome": "retrained", "exit_code": 3}
    )
    assert "| 15° | fnn | 5.00 | 4.00 |" in text and "`needle-force-15` v2 (fnn) → champion" in text
    # and the report gives every new trial's place
    assert "  - `t1`: used: train at 15°" in text
    assert f"  - `t2`: set aside at split: data/raw/cast-7/t2.*: {channels['reason']}" in text
    assert "  - `(whole batch)`: set aside at ingest: data/raw/bad: no batch.yaml" in text


def test_outcome_is_retrained_only_when_every_new_trial_was_used() -> None:
    clean = {"batches_set_aside": [], "trials_set_aside": []}
    assert retrain.outcome(0, clean) == (retrain.EXIT_RETRAINED, "retrained")
    assert retrain.outcome(2, clean)[0] == retrain.EXIT_FAILED
    # a batch the ledger does not know is not called used
    ghost = retrain.Pending("ghost", "data/raw/ghost", "new", ["data/raw/ghost: no batch.yaml"])
    report = retrain.summarise([ghost], [], None, None, {}, {})
    assert report["batches_set_aside"] == ["ghost"]
    assert retrain.outcome(0, report)[0] == retrain.EXIT_SET_ASIDE
    # and the report still shows what the check before the run found in it
    text = retrain.render({**report, "started": "2026-11-23T12:00:00Z", "outcome": "failed", "exit_code": 1})
    assert "  - data/raw/ghost: no batch.yaml" in text


RETRAIN = [sys.executable, "-m", "pipeline.cli", "retrain"]  # as cron runs it, in the project's folder


def retrain_env() -> dict[str, str]:
    return dict(os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}")


def retrain_cli(root: Path) -> subprocess.CompletedProcess[str]:
    """`needlecue retrain` in the project copy, as cron would run it."""
    return subprocess.run(
        RETRAIN,
        cwd=root,
        env=retrain_env(),
        capture_output=True,
        text=True,
        timeout=900,
    )


def new_cast(root: Path, batch_id: str, angle: int) -> None:
    """A lab drops one new simulated tissue cast (4 trials at one angle) into data/raw (`needlecue
    simulate-batch` in the project's folder, in this process: the retrains are what runs as cron would)."""
    with contextlib.chdir(root):
        done = CliRunner().invoke(
            app, ["simulate-batch", "data/raw", batch_id, "--angles", str(angle), "--trials", "4"]
        )
    assert done.exit_code == 0, done.output


@pytest.mark.slow
def test_retrain_follows_a_new_batch_and_nothing_else(
    tiny_registered: Registered, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Given a small project trained and registered end to end (shared: tests/conftest.py)
    root, _params = copy_registered(tiny_registered, tmp_path, monkeypatch)
    client = MlflowClient()
    champion_15 = client.get_model_version_by_alias("needle-force-15", "champion")
    champion_45 = client.get_model_version_by_alias("needle-force-45", "champion")

    # When nothing is new, retrain does nothing and registers nothing
    idle = retrain_cli(root)
    assert idle.returncode == retrain.EXIT_NOTHING, idle.stderr
    assert "nothing to do" in idle.stderr

    # When a new 15° cast and a broken batch arrive, and the retrain that takes them is killed half
    # way (during training)
    new_cast(root, "cast-7", 15)
    (root / "data" / "raw" / "broken").mkdir()
    (root / "data" / "raw" / "broken" / "batch.yaml").write_text("format: rig-log/1\nbatch_id: [\n")
    raw_before = tree_hash(root / "data" / "raw")
    killed = subprocess.Popen(
        RETRAIN,
        cwd=root,
        env=retrain_env(),
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    assert killed.stderr is not None
    said = []
    for line in killed.stderr:
        said.append(line)
        if "Running stage 'train@15" in line:
            os.killpg(killed.pid, signal.SIGKILL)
            break
    killed.wait(timeout=60)
    # Then the registry and the raw data are as they were
    assert killed.returncode == -signal.SIGKILL, "".join(said)
    assert len(client.search_model_versions("name = 'needle-force-15'")) == 1
    assert tree_hash(root / "data" / "raw") == raw_before
    # and it had parsed only the new batches; the known ones came from the ingest cache
    ingest_lines = [line for line in said if line.startswith("ingest [")]
    # 7 simulated batches (2 training casts-by-unit, 2 held-out, 2 new-unit held-out, 1 calibration)
    # + the two new ones
    assert len(ingest_lines) == 9, "".join(said)
    for line in ingest_lines:
        assert (": parsed" in line) == ("cast-7" in line or "broken" in line), line

    # When the next run resumes the job (its ingest already done: the new batches no longer differ
    # from the ingest cache)
    done = retrain_cli(root)
    # Then it retrained, with the broken batch set aside and reported (exit 3): the killed run's
    # batches are this run's
    assert done.returncode == retrain.EXIT_SET_ASIDE, done.stderr
    report = json.loads((root / "reports" / "retrain" / "latest.json").read_text())
    assert sorted(b["batch_id"] for b in report["batches"]) == ["broken", "cast-7"]
    assert report["batches_set_aside"] == ["broken"]
    assert not (root / retrain.UNFINISHED).exists()
    # only the angle with new data retrained
    assert report["angles_retrained"] == ["15"]
    assert {s for s in report["stages_run"] if s.startswith("train@")} == {
        "train@15-ls",
        "train@15-fnn",
        "train@15-lstm",
    }
    # a new version of needle-force-15 is registered; 45° keeps its model, which comes back with the
    # new cue pack (the angle estimator of every pack learned from the new 15° cast)
    assert sorted(report["registered"]) == ["15", "45"]
    entry = report["registered"]["15"]
    assert entry["version"] == 2
    repack = report["registered"]["45"]
    assert repack["model_sha256"] == champion_45.tags["needlecue.model_sha256"]
    assert repack["aliases"] == ["champion"] and "own model, packed anew" in repack["reason"]
    # the 15° champion moved only if the new version beat it on the external set
    champion_now = client.get_model_version_by_alias("needle-force-15", "champion")
    old_score = entry["previous_champion"]["external_nrmse_pct_mean"]
    if entry["external_nrmse_pct_mean"] < old_score:
        assert int(champion_now.version) == 2 and report["promoted"] == ["15", "45"]
    else:
        assert champion_now.version == champion_15.version and entry["aliases"] == ["challenger"]
        assert report["promoted"] == ["45"]
    assert (root / "reports" / "retrain" / "latest.md").read_text().startswith("# Retrain")

    # When a second retrain starts while one holds the lock, it exits cleanly and does nothing
    with retrain.lock(root / retrain.LOCK_FILE):
        busy = retrain_cli(root)
    assert busy.returncode == retrain.EXIT_BUSY
    assert "another retrain is running" in busy.stderr


def test_a_new_batch_that_split_sets_aside_makes_retrain_exit_3(tmp_path: Path) -> None:
    # given: a lab batch, and a new one at 30° whose estimator names its channels otherwise: ingest
    # and resample pass it, split sets it aside (its channels differ from the rest at 30°)
    from pipeline import ledger
    from pipeline.config import ResampleParams, SplitParams
    from pipeline.dataset import split
    from pipeline.reporting.ingest import write_reports
    from pipeline.rig.ingest import ingest_batches
    from pipeline.signals import resample

    raw = tmp_path / "raw"
    shutil.copytree(LAB_BATCH, raw / "lab-bench-a")
    new = shutil.copytree(LAB_BATCH, raw / "lab-bench-b")
    (new / "batch.yaml").write_text(
        (new / "batch.yaml").read_text().replace("lab-bench-a", "lab-bench-b").replace("bottom]", "back]")
    )
    (new / "trials.csv").write_text("trial_id,tissue_point,angle_deg\nt001,P1,30\n")
    for name in ("t002.fsr.csv", "t002.ref.csv", "t003.fsr.csv", "t003.ref.csv"):
        (new / name).unlink()
    fsr = new / "t001.fsr.csv"
    renamed = fsr.read_text().replace("t_ms,left,right,top,bottom", "t_ms,left,right,top,back")
    fsr.write_text(renamed.replace("0.7931", "0.7932", 1))  # another recording, not a copy
    quiet = lambda _m: None  # noqa: E731
    # when: the stages run on it and the ledger is built from their records
    result = ingest_batches([raw], tmp_path / "ingested", IngestParams(), log=quiet)
    write_reports(result, tmp_path / "reports", data_docs=False)
    rows = resample.run(tmp_path / "ingested", tmp_path / "resampled", ResampleParams(), log=quiet).rows
    manifest = split.run(tmp_path / "resampled", tmp_path / "processed", SplitParams(), log=quiet)
    records = {
        n: json.loads((tmp_path / "reports" / f"{n}.json").read_text()) for n in ("batches", "quarantine")
    }
    doc = ledger.document(
        ledger.build(records["batches"], records["quarantine"], rows, manifest, [], trained=[30, 45])
    )
    report = retrain.summarise([retrain.Pending("lab-bench-b", str(new), "new")], [], None, None, {}, doc)
    # then: the new trial is set aside at split, with the reason, and the retrain exits 3
    assert [(e["trial_id"], e["stage"]) for e in report["trials_set_aside"]] == [("t001", "split")]
    assert (
        "channels ['left', 'right', 'top', 'back'] differ"
        in report["trials_set_aside"][0]["where"][0]["reason"]
    )
    assert report["batches_set_aside"] == ["lab-bench-b"]
    assert retrain.outcome(0, report)[0] == retrain.EXIT_SET_ASIDE
