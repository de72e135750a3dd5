"""`needlecue ui`: MLflow's UI, in a real headless Chromium, opens on the runs of every angle and model
kind with their external NRMSE, best first (the lab's place to compare models)."""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import sys
from pathlib import Path

import pytest
from mlflow import MlflowClient

from needlecue_runtime.registry import store
from tests.helpers import descendants, free_port
from tests.projects import Registered, copy_registered

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
ROWS = """() => {
  const rows = {};
  for (const cell of document.querySelectorAll('[role=row][row-index] [col-id]')) {
    const i = Number(cell.closest('[role=row]').getAttribute('row-index'));
    (rows[i] = rows[i] || {})[cell.getAttribute('col-id')] = cell.innerText.trim();
  }
  return Object.keys(rows).sort((a, b) => a - b).map(i => rows[i]);
}"""
NAME, NRMSE = "attributes.`Run Name`", "metrics.`external_nrmse_pct_mean`"


@pytest.mark.slow
def test_the_ui_opens_on_every_angle_and_kind_with_its_external_nrmse(
    tiny_registered: Registered, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from playwright.sync_api import sync_playwright

    # given: the small project registered (two angles, three kinds)
    root, params = copy_registered(tiny_registered, tmp_path, monkeypatch)
    client = MlflowClient()
    runs = client.search_runs([client.get_experiment_by_name(store.EXPERIMENT).experiment_id])
    expected = {r.info.run_name: r.data.metrics["external_nrmse_pct_mean"] for r in runs}
    angles, kinds = params["train"]["angles"], params["train"]["kinds"]
    assert set(expected) == {f"{a:g}°-{k}" for a in angles for k in kinds}
    # when: `needlecue ui` serves the store and a browser opens the link it prints
    env = dict(os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}")
    port = free_port()
    cmd = [sys.executable, "-m", "pipeline.cli", "ui", "--port", str(port)]
    ui = subprocess.Popen(cmd, cwd=root, env=env, stdout=subprocess.PIPE, text=True, start_new_session=True)
    try:
        assert ui.stdout is not None
        link = ui.stdout.readline().strip()
        assert link.startswith("http://127.0.0.1:"), link
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=["--disable-gpu"], timeout=30_000)
            page = browser.new_page(viewport={"width": 1600, "height": 1000})
            page.goto(link)
            # the rows and the page's header render apart: on a busy machine the rows come first
            named = f"document.body.innerText.includes('{store.EXPERIMENT}')"
            ready = f"() => ({ROWS})().length >= {len(expected)} && {named}"
            page.wait_for_function(ready, timeout=60_000)
            rows = page.evaluate(ROWS)
            serving = list(descendants(ui.pid).values())
            shown = page.locator("body").inner_text()
            page.screenshot(path=str(tmp_path / "ui.png"))
            browser.close()
    finally:
        ui.terminate()
        ui.wait(timeout=60)
    # then: killed (SIGTERM), `needlecue ui` stopped the server it started: nothing answers on its port
    with socket.socket() as sock:
        assert sock.connect_ex(("127.0.0.1", port)) != 0, "the MLflow server outlived `needlecue ui`"
    # and: the server ran without MLflow's job runner (huey consumers for GenAI jobs, a registry runs none)
    assert any(" server " in line for line in serving), serving
    assert not [line for line in serving if "huey" in line], serving
    # and the page is the model-training view of needle-force's runs, one row per angle and kind,
    # each with its run's external NRMSE, best first
    assert "Model training" in shown and store.EXPERIMENT in shown
    seen = {row[NAME].splitlines()[-1]: float(row[NRMSE]) for row in rows}
    assert seen.keys() == expected.keys()
    assert all(abs(seen[name] - value) < 1e-9 for name, value in expected.items()), (seen, expected)
    order = [row[NAME].splitlines()[-1] for row in rows]
    assert order == sorted(expected, key=expected.get)
