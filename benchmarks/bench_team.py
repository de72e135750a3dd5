"""The team stack against a local sqlite store: registration time per model, and champion fetches under
load.

Needs the project's outputs (`make repro`). Starts a throw-away team stack (PostgreSQL, SeaweedFS,
MLflow with basic auth) on free loopback ports in a temp folder, then:
1. runs the register stage's command (tracking every trained model, registering each angle's best
   and the unit calibrations) into a fresh sqlite store and into the stack, as the lab, REGISTER_ROUNDS
   times each into fresh stores, alternating, and prints the median seconds per tracked model of each and
   their ratio;
2. has SIMULATORS threads, each with its own cache and the simulator's read-only credentials, fetch
   `needle-force-30@champion` at once, ROUNDS times for each of two ways (the files the client runs,
   as `fetch` does, and the whole logged model, as it did before), alternating, and prints p50 and
   p99 of each round and the median of each over the rounds; every fetch must succeed.
All figures come from this one run. The stack is stopped and deleted at the end.
"""

from __future__ import annotations

import os
import statistics
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from pipeline.team.stack import Stack, free_base_port  # noqa: E402

REGISTER_ROUNDS = 1  # each is the whole register stage (18 models here): minutes against the server
ROUNDS = 3  # fetch rounds
SIMULATORS = 50
REGISTER = [
    sys.executable, "-m", "pipeline.run", "register", "models", "data/processed", "data/predictions",
    "data/calibration", "reports",
]  # fmt: skip


def register(env: dict[str, str], out: Path) -> tuple[float, int]:
    """Seconds for one register run into the store `env` names, and how many models it tracked."""
    t0 = time.perf_counter()
    done = subprocess.run(
        [*REGISTER, str(out)], cwd=ROOT, env={**os.environ, **env}, capture_output=True, text=True
    )
    took = time.perf_counter() - t0
    if done.returncode != 0:
        raise SystemExit(f"register failed:\n{done.stdout[-2000:]}\n{done.stderr[-2000:]}")
    return took, done.stderr.count("register: tracked ") + done.stdout.count("register: tracked ")


def main() -> None:
    if not (ROOT / "models").is_dir():
        raise SystemExit("no trained models: run `make repro` first")
    with tempfile.TemporaryDirectory() as tmp:
        tmp_path = Path(tmp)
        sqlite_s, server_s = [], []
        for i in range(REGISTER_ROUNDS):
            stack = Stack(tmp_path / f"stack-{i}")
            stack.init(base_port=free_base_port())
            stack.start(progress=lambda _m: None)
            try:
                uri = f"sqlite:///{tmp_path / f'mlflow-{i}.db'}"
                took, n = register(
                    {"MLFLOW_TRACKING_URI": uri, "MLFLOW_REGISTRY_URI": uri}, tmp_path / f"r{i}.json"
                )
                sqlite_s.append(took / n)
                lab = stack.role_env("lab")
                took, n = register(
                    {**lab, "MLFLOW_REGISTRY_URI": lab["MLFLOW_TRACKING_URI"]}, tmp_path / f"s{i}.json"
                )
                server_s.append(took / n)
                print(f"round {i + 1}: register, per tracked model ({n}): sqlite {sqlite_s[-1]:.2f} s, "
                      f"server {server_s[-1]:.2f} s")  # fmt: skip
                if i == REGISTER_ROUNDS - 1:
                    fetch_load(stack, tmp_path)
            finally:
                stack.stop(purge=True)
        a, b = statistics.median(sqlite_s), statistics.median(server_s)
        n = REGISTER_ROUNDS
        print(f"register per model, median of {n}: sqlite {a:.2f} s, server {b:.2f} s, ratio {b / a:.2f}")


def fetch_load(stack: Stack, tmp_path: Path) -> None:
    """ROUNDS rounds of SIMULATORS fetches at once, alternating what a fetch downloads: the files the
    client runs (MLmodel and model.onnx, the default) and, for comparison, the whole logged model."""
    from pipeline.client import cache, fetch

    os.environ.update(stack.role_env("simulator"))
    ways = {"client's files": cache.MODEL_FILES, "whole model": None}
    p50s: dict[str, list[float]] = {way: [] for way in ways}
    p99s: dict[str, list[float]] = {way: [] for way in ways}
    for r in range(ROUNDS):
        for way, files in ways.items():
            cache.MODEL_FILES = files  # what fetch() passes as `only`

            def one(i: int, r: int = r, way: str = way) -> float:
                t0 = time.perf_counter()
                fetch(30, cache_dir=tmp_path / f"cache-{r}-{way}-{i}", tracking_uri=stack.tracking_uri)
                return time.perf_counter() - t0

            with ThreadPoolExecutor(max_workers=SIMULATORS) as pool:
                times = sorted(pool.map(one, range(SIMULATORS)))
            p50s[way].append(statistics.median(times))
            p99s[way].append(times[int(0.99 * (len(times) - 1))])
            print(f"fetch round {r + 1}, {way}: {SIMULATORS} at once, 0 errors: "
                  f"p50 {p50s[way][-1]:.2f} s, p99 {p99s[way][-1]:.2f} s")  # fmt: skip
    cache.MODEL_FILES = ways["client's files"]
    for way in ways:
        p50, p99 = statistics.median(p50s[way]), statistics.median(p99s[way])
        print(f"fetch under load, {way}, median of {ROUNDS} rounds: p50 {p50:.2f} s, p99 {p99:.2f} s")


if __name__ == "__main__":
    main()
