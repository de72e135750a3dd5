"""The registered champion through MLflow's own tools (docs/deploy.md): `mlflow.pyfunc.load_model` and
`mlflow models serve` on the estimator's raw readings give the ForceClient's force, and a wrong input is
a 4xx with a message, not a number."""

from __future__ import annotations

import contextlib
import json
import os
import subprocess
import sys
import time
import urllib.error
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from needlecue_runtime.features import unit_inputs
from tests.deploy.builders import Champion, client_forces, pyfunc_champion, raw_feed
from tests.helpers import free_port, stop_group

SERVE_START_S = 120.0


def test_pyfunc_on_raw_readings_gives_the_clients_force(champion: Champion, tmp_path: Path) -> None:
    # given: the champion, its calibrated unit, and a held-out trial of the unit's raw readings
    feed = raw_feed(champion)
    # when: MLflow's own loader runs it, and the ForceClient steps through the trial
    model = pyfunc_champion(champion)
    got = np.asarray(model.predict(feed)["force_n"])
    expected = client_forces(champion, tmp_path / "cache")
    # then: the same force, within 1e-5 N, and the calibration mattered
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-5)
    uncalibrated = dict(
        feed,
        **dict(zip(("unit_matrix", "unit_offset", "unit_circuit"), unit_inputs(None, None, 3), strict=True)),
    )
    assert np.abs(np.asarray(model.predict(uncalibrated)["force_n"]) - expected).max() > 1e-3


def test_pyfunc_reads_adc_counts_as_their_volts(champion: Champion) -> None:
    # given: the trial as a 10-bit ADC on 5 V would send it (integer counts), and the same in volts
    per_count = 5.0 / 1023
    feed = raw_feed(champion)
    counts = {k: np.rint(feed[k] / per_count) for k in ("reading", "rest_reading")}
    as_counts = dict(feed, **counts, volts_per_count=np.array([per_count]))
    as_volts = dict(feed, **{k: v * per_count for k, v in counts.items()})
    # when: the champion reads both
    model = pyfunc_champion(champion)
    got = [np.asarray(model.predict(f)["force_n"]) for f in (as_counts, as_volts)]
    # then: the same force
    np.testing.assert_allclose(got[0], got[1], rtol=0, atol=1e-6)


@contextlib.contextmanager
def served(uri: str, root: Path) -> Iterator[str]:
    """`mlflow models serve` of the champion on 127.0.0.1 (local env), stopped with its workers."""
    port = free_port()
    log_path = root / "serve.log"
    env = {k: v for k, v in os.environ.items() if not k.startswith("MLFLOW_")}
    env |= {"MLFLOW_TRACKING_URI": uri, "MLFLOW_REGISTRY_URI": uri}
    env["PATH"] = (
        f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"  # its uvicorn, as activated
    )
    with log_path.open("wb") as log:
        proc = subprocess.Popen(
            [
                *(
                    sys.executable,
                    "-m",
                    "mlflow",
                    "models",
                    "serve",
                    "-m",
                    "models:/needle-force-30@champion",
                ),
                *("--env-manager", "local", "-h", "127.0.0.1", "-p", str(port), "-w", "1"),
            ],
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
            env=env,
        )
        try:
            url = f"http://127.0.0.1:{port}"
            deadline = time.monotonic() + SERVE_START_S
            while True:
                if proc.poll() is not None:
                    pytest.fail(
                        f"mlflow models serve exited {proc.returncode}:\n{log_path.read_text()[-3000:]}"
                    )
                with contextlib.suppress(OSError), urllib.request.urlopen(f"{url}/ping", timeout=2) as r:
                    if r.status == 200:
                        break
                if time.monotonic() > deadline:
                    pytest.fail(f"not serving after {SERVE_START_S:g} s:\n{log_path.read_text()[-3000:]}")
                time.sleep(0.25)
            yield url
        finally:
            stop_group(proc)


def post(url: str, body: dict) -> tuple[int, dict]:
    request = urllib.request.Request(
        f"{url}/invocations", json.dumps(body).encode(), {"Content-Type": "application/json"}
    )
    try:
        with urllib.request.urlopen(request, timeout=30) as r:
            return r.status, json.loads(r.read())
    except urllib.error.HTTPError as e:
        return e.code, json.loads(e.read() or b"{}")


def test_mlflow_models_serve_on_raw_readings_gives_the_clients_force_and_refuses_a_wrong_shape(
    champion: Champion, tmp_path: Path
) -> None:
    # given: the champion served the standard MLflow way, and a held-out trial of the calibrated unit
    feed = raw_feed(champion)
    expected = client_forces(champion, tmp_path / "cache")
    with served(champion.uri, tmp_path) as url:
        # when: a simulator posts the raw readings as JSON, and then a window of two channels, and
        # a window of the wrong length
        status, answer = post(url, {"inputs": {k: v.tolist() for k, v in feed.items()}})
        two = dict(feed, reading=feed["reading"][:, :, :2], rest_reading=feed["rest_reading"][:, :, :2])
        bad_channels = post(url, {"inputs": {k: v.tolist() for k, v in two.items()}})
        short = dict(feed, reading=feed["reading"][:, :3], rest_reading=feed["rest_reading"][:, :3])
        bad_window = post(url, {"inputs": {k: v.tolist() for k, v in short.items()}})
    # then: the client's force within 1e-5 N; each wrong input a 400 whose message says which shape
    # was sent and which the signature expects
    assert status == 200, answer
    np.testing.assert_allclose(np.asarray(answer["predictions"]["force_n"]), expected, rtol=0, atol=1e-5)
    for (code, body), shape in ((bad_channels, "(90, 6, 2)"), (bad_window, "(90, 3, 3)")):
        assert code == 400, body
        assert f"Shape of input {shape} does not match expected shape (-1, 6, 3)" in body["message"], body
