"""What MLflow's job runner costs a registry server (`SERVER_ENV` in `pipeline/registry/ui.py`).

Starts `mlflow server` on one sqlite store (`needlecue ui`'s command, 127.0.0.1 only), as MLflow
starts it by default and with `SERVER_ENV` (the job runner off), in turns. For each start: seconds
until /health answers, then, `--settle` seconds later, the processes in its session and their
resident memory.

Run with `.venv/bin/python benchmarks/bench_registry_server.py [--runs N]` (about 35 s a run: two
starts). Prints one line per start and the medians per setting.
"""

from __future__ import annotations

import argparse
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

import psutil

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from pipeline.registry.ui import SERVER_ENV, server_command  # noqa: E402
from tests.helpers import free_port  # noqa: E402

SETTINGS = {"MLflow's default": {}, "SERVER_ENV": SERVER_ENV}


def start(uri: str, extra: dict[str, str], settle_s: float) -> tuple[float, int, float]:
    """Seconds to answer, processes, resident MB of one server start; the server is stopped after."""
    port = free_port()
    env = {**{k: v for k, v in os.environ.items() if not k.startswith("MLFLOW_")}, **extra}
    t0 = time.perf_counter()
    proc = subprocess.Popen(
        server_command(uri, "127.0.0.1", port),
        env=env,
        start_new_session=True,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        while True:
            if proc.poll() is not None:
                raise SystemExit(f"mlflow server exited with {proc.returncode}")
            try:
                urllib.request.urlopen(f"http://127.0.0.1:{port}/health", timeout=2).close()
                break
            except OSError:
                time.sleep(0.1)
        up_s = time.perf_counter() - t0
        time.sleep(settle_s)
        group = [p for p in psutil.process_iter() if _session(p) == proc.pid]
        rss = sum(p.memory_info().rss for p in group if p.is_running())
        return up_s, len(group), rss / 2**20
    finally:
        os.killpg(proc.pid, signal.SIGTERM)
        proc.wait(timeout=60)


def _session(p: psutil.Process) -> int | None:
    try:
        return os.getsid(p.pid)
    except OSError:
        return None


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--settle", type=float, default=8.0, help="seconds after /health to count")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        uri = f"sqlite:///{Path(tmp) / 'mlflow.db'}"
        start(uri, SERVER_ENV, 0)  # makes the store's tables, not timed
        figures: dict[str, list[tuple[float, int, float]]] = {name: [] for name in SETTINGS}
        for run in range(args.runs):
            for name, extra in SETTINGS.items():
                figures[name].append(start(uri, extra, args.settle))
                up_s, n, mb = figures[name][-1]
                print(f"run {run}: {name:17s} up in {up_s:4.1f} s, {n:2d} processes, {mb:5.0f} MB")
    print("medians:")
    for name, rows in figures.items():
        up_s, n, mb = (statistics.median(col) for col in zip(*rows, strict=True))
        print(f"  {name:17s} up in {up_s:4.1f} s, {n:2.0f} processes, {mb:5.0f} MB")


if __name__ == "__main__":
    main()
