"""The published champion in a second runtime (docs/deploy.md): onnxruntime for Node.js, through the
JavaScript client in deploy/node, checks the lab's signature and every hash and gives the Python
ForceClient's force on a calibrated unit's held-out trial."""

from __future__ import annotations

import base64
import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from needlecue_runtime.registry import manifest as signed
from needlecue_runtime.registry import store
from pipeline.modelling.checkpoint import checkpoint_sha256
from pipeline.team.publish import Target, put_version
from tests.deploy.bucket import FolderBucket
from tests.deploy.builders import UNIT, Champion, client_forces

NODE_DIR = Path(__file__).resolve().parents[2] / "deploy" / "node"
NODE_S = 120  # a replay of one trial, the runtime's start included: a second or two here


def node_ready() -> bool:
    return shutil.which("node") is not None and (NODE_DIR / "node_modules" / "onnxruntime-node").is_dir()


pytestmark = pytest.mark.skipif(not node_ready(), reason="needs node and `make setup-node` (deploy/node)")


def publish_to(folder: Path, uri: str, angle: str = "30", unit: str = UNIT) -> str:
    """The champion at `angle` and `unit`'s calibration published, signed, into a bucket copy `folder`,
    as the lab's publisher does; returns the public key simulators hold (base64)."""
    private = signed.new_private_key()
    target = Target(FolderBucket(folder), "published", private, "test")
    client = store.connect(uri)
    for name, alias in ((f"needle-force-{angle}", "champion"), (f"needle-unit-{unit}", "current")):
        put_version(store.alias_version(client, name, alias), alias, uri, target)
    return base64.b64encode(signed.public_of(private)).decode()


def replay_in_node(
    bucket: Path, key: str, trial: pd.DataFrame, tmp_path: Path, unit: str | None, angle: str = "30"
) -> dict:
    """What deploy/node/replay.mjs gives on `trial`'s readings (fsr1..3) with the published champion at
    `angle`, for `unit` (None: uncalibrated)."""
    recording = tmp_path / "recording.json"
    volts = trial[["fsr1", "fsr2", "fsr3"]].to_numpy().tolist()
    recording.write_text(json.dumps({"t_s": trial["t_s"].tolist(), "volts": volts}))
    args = [
        "node",
        str(NODE_DIR / "replay.mjs"),
        str(bucket),
        angle,
        key,
        str(recording),
        *([unit] if unit else []),
    ]
    done = subprocess.run(args, capture_output=True, text=True, timeout=NODE_S, check=False)
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout)


def test_node_runs_the_published_champion_as_the_python_client_does(
    champion: Champion, tmp_path: Path
) -> None:
    # given: the champion and its unit's calibration published to a bucket copy, and a held-out trial
    bucket = tmp_path / "bucket"
    key = publish_to(bucket, champion.uri)
    # when: the JavaScript client replays the trial for the calibrated unit, and the Python client does
    got = replay_in_node(bucket, key, champion.trial, tmp_path, UNIT)
    uncalibrated = replay_in_node(bucket, key, champion.trial, tmp_path, None)
    expected = client_forces(champion, tmp_path / "cache")
    # then: calibrated, the same model, the same force within 1e-5 N; the calibration mattered
    assert got["calibrated"] and got["model"]["checkpoint_sha256"] == checkpoint_sha256(champion.checkpoint)
    assert got["targets"] == ["fx", "fy", "fz"]
    np.testing.assert_allclose(np.asarray(got["force_n"]), expected, rtol=0, atol=1e-5)
    assert not uncalibrated["calibrated"]
    assert np.abs(np.asarray(uncalibrated["force_n"]) - expected).max() > 1e-3


def test_node_refuses_a_changed_graph_and_a_foreign_signature(champion: Champion, tmp_path: Path) -> None:
    # given: a bucket copy whose graph object was changed, and the public key of another lab
    bucket = tmp_path / "bucket"
    key = publish_to(bucket, champion.uri)
    other = base64.b64encode(signed.public_of(signed.new_private_key())).decode()
    # when / then: another lab's key refuses the manifest; a changed object refuses the graph
    for bad_key, damage, expected in (
        (other, False, "not signed by the lab's key"),
        (key, True, "not the manifest's"),
    ):
        if damage:
            document = json.loads((bucket / "manifests/needle-force-30/champion.json").read_text())
            graph = bucket / "objects/sha256" / document["manifest"]["files"]["model.onnx"]["sha256"]
            graph.write_bytes(graph.read_bytes()[:-1] + b"\0")
        recording = tmp_path / "recording.json"
        recording.write_text(json.dumps({"t_s": [0.0], "volts": [[1.0, 1.0, 1.0]]}))
        args = ["node", str(NODE_DIR / "replay.mjs"), str(bucket), "30", bad_key, str(recording)]
        done = subprocess.run(args, capture_output=True, text=True, timeout=NODE_S, check=False)
        assert done.returncode != 0 and expected in done.stderr, done.stderr[-2000:]


def test_node_gives_a_model_of_fz_one_value_per_sample(fz_champion: Champion, tmp_path: Path) -> None:
    # given: the champion of a lab whose reference recorded fz alone, published with its unit
    bucket = tmp_path / "bucket"
    key = publish_to(bucket, fz_champion.uri)
    # when: the JavaScript client replays a held-out trial for the calibrated unit, as Python does
    got = replay_in_node(bucket, key, fz_champion.trial, tmp_path, UNIT)
    expected = client_forces(fz_champion, tmp_path / "cache")
    # then: the targets it read from the description, and one value per sample: Python's fz
    assert got["calibrated"] and got["targets"] == ["fz"]
    assert len(got["force_n"]) == len(fz_champion.trial) and all(len(f) == 1 for f in got["force_n"])
    np.testing.assert_allclose(np.asarray(got["force_n"]), expected, rtol=0, atol=1e-5)


def test_node_refuses_a_description_whose_targets_are_not_axes_in_order(tmp_path: Path) -> None:
    # given / when: the description check of the JavaScript client, on good and bad targets
    script = (
        f"import {{ targetsOf }} from {json.dumps((NODE_DIR / 'needlecue.mjs').as_uri())};\n"
        "for (const t of [['fz'], ['fx', 'fy', 'fz'], ['fz', 'fx'], [], ['fz', 'fz'], 'fz', undefined]) {\n"
        "  try { console.log(JSON.stringify(targetsOf({ targets: t }, 'm'))); }\n"
        "  catch (e) { console.log(e.message); }\n"
        "}\n"
    )
    done = subprocess.run(
        ["node", "--input-type=module", "-e", script],
        capture_output=True,
        text=True,
        timeout=NODE_S,
        check=False,
    )
    # then: the subsets in order pass; anything else is one line naming the field
    assert done.returncode == 0, done.stderr[-2000:]
    lines = done.stdout.splitlines()
    assert lines[:2] == ['["fz"]', '["fx","fy","fz"]'] and len(lines) == 7
    assert all(line.startswith("m: field needlecue.targets is ") for line in lines[2:]), lines
