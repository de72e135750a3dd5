"""The live tests' real processes: `needlecue emulate-rig` (or `emulate-board`, the firmware on an
emulated board) on a pseudo-terminal and `needlecue live` reading it, with the unit's calibration, a
session folder and the page on a free port."""

from __future__ import annotations

import contextlib
import http.client
import json
import os
import subprocess
import sys
import time
import urllib.request
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from typer.testing import CliRunner, Result

from pipeline.cli import app
from tests.live.conftest import ADC_BITS, UNIT, LiveModel, write_trials

NEEDLECUE = [sys.executable, "-m", "pipeline.cli"]


@dataclass(frozen=True)
class Running:
    live: subprocess.Popen[str]
    rig: subprocess.Popen[str]
    files: list[Path]  # the trials the rig plays
    url: str  # the trainee page
    session: Path  # the recording's folder
    settings: dict[str, str]  # what both run with on top of this environment: the model's store, a cache

    def replay(self, *args: str) -> Result:
        """`needlecue replay ARGS` with the session's settings, in this process (a process of its own
        would only import the stack again); it must succeed."""
        done = CliRunner().invoke(app, ["replay", *args], env=self.settings)
        assert done.exit_code == 0, done.output
        return done


def settings_for(model: LiveModel, tmp_path: Path) -> dict[str, str]:
    """The model's store and a model cache of the test's own, as environment variables."""
    return {
        "MLFLOW_TRACKING_URI": model.uri,
        "MLFLOW_REGISTRY_URI": model.uri,
        "NEEDLECUE_MODEL_CACHE": str(tmp_path / "cache"),
    }


def display_url(proc: subprocess.Popen[str], limit_s: float = 60) -> str:
    end = time.monotonic() + limit_s
    assert proc.stdout is not None
    said = []
    while time.monotonic() < end:
        line = proc.stdout.readline()
        said.append(line)
        if line.startswith("display: "):
            return line.split()[1]
        if not line and proc.poll() is not None:
            break
    raise AssertionError(f"needlecue live printed no display URL (exit {proc.poll()}): {''.join(said)}")


@contextlib.contextmanager
def rig_and_live(
    model: LiveModel,
    tmp_path: Path,
    angles: list[float],
    rig_args: list[str],
    live_args: list[str],
    rig: str = "emulate-rig",
    adc_bits: int = ADC_BITS,
    withdraw: bool = False,
) -> Iterator[Running]:
    """The rig playing one synthetic trial per angle (2.5 s rests), live on its link; both are killed
    on the way out if still running."""
    files = write_trials(tmp_path / "held", angles, adc_bits=adc_bits, withdraw=withdraw)
    link, session = tmp_path / "rig", tmp_path / "session"
    settings = settings_for(model, tmp_path)
    env = {**os.environ, **settings}
    board = subprocess.Popen(
        [*NEEDLECUE, rig, *map(str, files), "--link", str(link), "--pause", "2.5", *rig_args],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    live = None
    try:
        deadline = time.monotonic() + 30
        while not link.exists() and time.monotonic() < deadline:
            time.sleep(0.05)
        live = subprocess.Popen(
            [*NEEDLECUE, "live", "--port", str(link), "--model-dir", str(model.model_dir), "--unit", UNIT,
             "--record", str(session), "--http-port", "0", "--reset-wait", "0.5", *live_args],
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )  # fmt: skip
        yield Running(live, board, files, display_url(live), session, settings)
    finally:
        for proc in (live, board):
            if proc is not None and proc.poll() is None:
                proc.kill()
                proc.wait(timeout=10)


def watch_problems(run: Running, limit_s: float) -> set[str]:
    """The problem keys the page's state showed, polled until live ends (at most `limit_s`)."""
    seen: set[str] = set()
    end = time.monotonic() + limit_s
    while run.live.poll() is None and time.monotonic() < end:
        try:
            with urllib.request.urlopen(run.url + "state", timeout=2) as r:
                seen |= set(json.loads(r.read()).get("problems") or {})
        except (OSError, http.client.HTTPException):
            pass  # the session ended between two polls, or in the middle of one
        time.sleep(0.05)
    return seen
