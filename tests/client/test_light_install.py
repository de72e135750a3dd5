"""The client on a simulator's install, for real: a fresh venv holding the client's distribution alone
(`pip install ./client`, no PYTHONPATH), fetching a model and an estimator unit's calibration through a
real MLflow server over HTTP and stepping them.

What this test does is what docs/client.md's "Installing just the client on a simulator" tells a simulator
maker to do; change one with the other. Slow (it builds a venv: about a minute).
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import subprocess
import sys
import time
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from needlecue_runtime.features import InputTransform
from needlecue_runtime.registry import mlflow_env, store
from needlecue_runtime.unit_calibration import parse_unit
from pipeline.config import CuesParams
from pipeline.cues.packs import build_cue_pack
from pipeline.modelling import export
from pipeline.modelling.fit import fit
from pipeline.modelling.predictor import Predictor
from pipeline.registry import calibrations
from pipeline.registry.ui import SERVER_ENV
from tests.client.builders import TINY, cue_predictions, cue_trials, unit_document
from tests.helpers import free_port, stop_group

ROOT = Path(__file__).resolve().parents[2]
CLIENT = ROOT / "client"  # the client's distribution (client/pyproject.toml)
# what a simulator must not get: the training package and the heavy libraries it pulls
HEAVY = ("pipeline", "torch", "sklearn", "dvc", "typer", "matplotlib", "great_expectations", "pandas")
VOLTS = [0.4, 0.5, 0.6]
UNIT = "est-light-1"
MIX = [[1.08, 0.05, 0.0], [0.0, 0.93, 0.04], [-0.03, 0.0, 1.1]]
SERVER_START_S = 90.0  # a fresh sqlite store is migrated at start-up: seconds, not minutes
INSTALL_S = 300.0  # venv and pip from the index, once per run of this test

# What a simulator runs, in the light venv.
SIMULATOR = """
import importlib.util, json, sys
from needlecue_client import ForceClient

uri, cache, heavy, volts = sys.argv[1], sys.argv[2], sys.argv[3].split(","), json.loads(sys.argv[4])
UNIT = sys.argv[5]
client = ForceClient.from_registry(30, tracking_uri=uri, cache_dir=cache, unit_id=UNIT)
client.check_stream(list(client.channels), client.rate_hz)
client.reset()
frame = client.step(volts)
print(json.dumps({
    "force_n": frame.force_n.tolist(),
    "cue": None if frame.cue is None else frame.cue.cue,
    "version": client.version,
    "calibration": client.calibration,
    "loaded": sorted(m for m in heavy if m in sys.modules),
    "installed": sorted(m for m in heavy if importlib.util.find_spec(m) is not None),
}))
"""


def _run(
    cmd: list[str], timeout: float, env: dict[str, str] | None = None, cwd: Path | None = None
) -> subprocess.CompletedProcess[str]:
    """Run `cmd` to its end within `timeout` seconds; a failure shows its output."""
    run = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=env, cwd=cwd, check=False)
    assert run.returncode == 0, (
        f"{cmd[:4]} exited {run.returncode}:\n{run.stdout[-3000:]}\n{run.stderr[-3000:]}"
    )
    return run


@contextlib.contextmanager
def mlflow_server(root: Path) -> Iterator[tuple[str, subprocess.Popen[bytes]]]:
    """`mlflow server` (the project's venv) on a sqlite store in `root`, serving its artifacts from
    `root/artifacts`, on 127.0.0.1 only; started in a session of its own, stopped with all its workers."""
    port = free_port()
    log = (root / "server.log").open("wb")
    proc = subprocess.Popen(
        [
            *(sys.executable, "-m", "mlflow", "server"),
            *("--backend-store-uri", f"sqlite:///{root / 'mlflow.db'}"),
            *("--artifacts-destination", (root / "artifacts").as_uri()),
            "--serve-artifacts",
            *("--host", "127.0.0.1", "--port", str(port), "--workers", "1"),
        ],
        stdout=log,
        stderr=subprocess.STDOUT,
        start_new_session=True,  # its own process group: the workers it forks are stopped with it
        env={**{k: v for k, v in os.environ.items() if not k.startswith("MLFLOW_")}, **SERVER_ENV},
    )
    try:
        yield f"http://127.0.0.1:{port}", proc
    finally:
        stop_group(proc)
        log.close()


def _wait_until_up(uri: str, proc: subprocess.Popen[bytes], log: Path) -> None:
    deadline = time.monotonic() + SERVER_START_S
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            pytest.fail(f"mlflow server exited {proc.returncode}:\n{log.read_text()[-3000:]}")
        with contextlib.suppress(OSError), urllib.request.urlopen(f"{uri}/health", timeout=2) as r:
            if r.status == 200:
                return
        time.sleep(0.25)
    pytest.fail(f"mlflow server not up after {SERVER_START_S:g} s:\n{log.read_text()[-3000:]}")


def _register_through(uri: str) -> tuple[dict, dict, str]:
    """A tiny 30° LS model with a cue pack, logged and registered as needle-force-30@champion through
    the server (its artifacts uploaded to it), and a unit calibrated with it as needle-unit-<UNIT>@current;
    returns the checkpoint, the unit's document and the experiment's artifact location."""
    import mlflow

    train = cue_trials(30, 3)
    checkpoint = fit("ls", TINY["ls"], train).checkpoint
    pack = build_cue_pack({30: train}, 30, CuesParams(), cue_predictions(checkpoint, {30: train}))
    client = store.connect(uri)
    exp_id = store.experiment_id(client)  # over HTTP the server picks the location: its artifact proxy
    name = store.model_name(30)
    with mlflow_env.fluent(client.tracking_uri):
        with mlflow.start_run(experiment_id=exp_id):
            info = export.log_onnx_model(checkpoint, pack)
        version = mlflow.register_model(info.model_uri, name).version
    client.set_registered_model_alias(name, store.CHAMPION, version)
    doc = unit_document(UNIT, {30: checkpoint}, MIX)
    unit = parse_unit(doc, "a test document")
    calibrations.register_unit(client, unit, calibrations.document_bytes(doc), lambda _m: None)
    return checkpoint, doc, client.get_experiment(exp_id).artifact_location


@pytest.mark.slow
def test_a_venv_of_the_client_distribution_alone_fetches_through_a_server_and_steps(tmp_path: Path) -> None:
    started = time.monotonic()
    server_root = tmp_path / "server"
    server_root.mkdir()
    with mlflow_server(server_root) as (uri, server):
        # given: the light venv of a simulator, built while the server starts
        venv = tmp_path / "venv"
        _run([sys.executable, "-m", "venv", str(venv)], timeout=120)
        python = str(venv / "bin" / "python")
        pip_log = tmp_path / "pip.log"
        # a copy, as a simulator maker would have it: building leaves an egg-info beside the sources
        source = tmp_path / "needlecue-client"
        shutil.copytree(CLIENT, source, ignore=shutil.ignore_patterns("__pycache__", "build", "*.egg-info"))
        with pip_log.open("wb") as log:
            pip = subprocess.Popen(
                [python, "-m", "pip", "install", "-q", str(source)],
                stdout=log,
                stderr=subprocess.STDOUT,
            )
        try:
            # and, meanwhile: a model registered through the server, its artifacts served by it
            _wait_until_up(uri, server, server_root / "server.log")
            checkpoint, doc, artifacts = _register_through(uri)
            assert artifacts.startswith("mlflow-artifacts:"), artifacts
            code = pip.wait(timeout=max(INSTALL_S - (time.monotonic() - started), 1.0))
        finally:
            if pip.poll() is None:
                pip.kill()
                pip.wait()
        assert code == 0, f"pip install ./client exited {code}:\n{pip_log.read_text()[-3000:]}"

        # when: the simulator, in the light venv (nothing on PYTHONPATH), fetches and steps it
        env = {k: v for k, v in os.environ.items() if not k.startswith(("MLFLOW_", "PYTHON"))}
        cache = tmp_path / "cache"
        run = _run(
            [python, "-c", SIMULATOR, uri, str(cache), ",".join(HEAVY), json.dumps(VOLTS), UNIT],
            timeout=120,
            env=env,
            cwd=tmp_path,  # not the checkout: what runs is what pip installed
        )
    out = json.loads(run.stdout.splitlines()[-1])
    # then: the venv really is light (nor has it the training package), the model and the unit's
    # calibration came through the server (a version made from a plain artifact folder), and the force
    # is the model's through the calibration
    assert out["installed"] == [] and out["loaded"] == [], out
    assert (out["version"]["version"], out["version"]["tracking_uri"]) == ("1", uri)
    assert (out["calibration"]["name"], out["calibration"]["version"]) == (f"needle-unit-{UNIT}", "1")
    assert out["calibration"]["source"].startswith("mlflow-artifacts:"), out["calibration"]
    assert (cache / "needle-force-30" / "champion" / "model.onnx").is_file()
    assert (cache / f"needle-unit-{UNIT}" / "current" / "calibration.json").is_file()
    transform = InputTransform.from_dict(doc["transforms"]["ls"])
    expected = Predictor(checkpoint).predict_arrays(np.array([VOLTS]), transform=transform)[0]
    np.testing.assert_allclose(out["force_n"], expected, rtol=1e-4, atol=1e-6)
    assert out["cue"] == "wait"
    print(f"light install, server and fetch: {time.monotonic() - started:.0f} s")
