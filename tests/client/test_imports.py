"""The client stays light: importing it and running a model with a unit's calibration loads none of
the training pipeline's heavy dependencies, so a simulator can install numpy, onnxruntime, pyyaml and
mlflow-skinny alone."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from tests.client.builders import Registered, unit_document

HEAVY = ("pipeline", "torch", "sklearn", "dvc", "typer", "matplotlib", "great_expectations", "pandas")
ROOT = Path(__file__).resolve().parents[2]

# Run in a fresh interpreter: this test process has imported all of them already.
SCRIPT = """
import json, sys
HEAVY = {heavy!r}

def loaded():
    return sorted(m for m in HEAVY if m in sys.modules)

import needlecue_client
after_import = loaded()
from needlecue_client import ForceClient

client = ForceClient.from_dir(sys.argv[1], calibration=sys.argv[2])
client.reset()
frame = client.step([0.6, 0.6, 0.6])
print(json.dumps({{
    "calibrated": client.calibrated,
    "after_import": after_import,
    "after_step": loaded(),
    "force_n": frame.force_n.tolist(),
    "cue": None if frame.cue is None else frame.cue.cue,
    "onnxruntime": "onnxruntime" in sys.modules,
}}))
"""


def test_importing_and_running_the_client_loads_no_heavy_dependency(
    registered: Registered, fetched: Path, tmp_path: Path
) -> None:
    # given: a fetched model folder (an LSTM with a cue pack), a unit's calibration made with it, and a
    # fresh interpreter
    calibration = tmp_path / "calibration.json"
    calibration.write_text(json.dumps(unit_document("est-i1", {30: registered.checkpoint})))
    # when: it imports needlecue_client, loads the folder with the calibration and steps one sample
    run = subprocess.run(
        [sys.executable, "-c", SCRIPT.format(heavy=HEAVY), str(fetched), str(calibration)],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=120,
        check=False,
    )
    assert run.returncode == 0, run.stderr
    out = json.loads(run.stdout.splitlines()[-1])
    # then: a force and a cue came out of onnxruntime and the cue tracker, and none of the heavy
    # modules was imported, neither by the import nor by running the model
    assert len(out["force_n"]) == 3 and out["cue"] == "wait" and out["onnxruntime"] and out["calibrated"]
    assert out["after_import"] == [] and out["after_step"] == [], out
