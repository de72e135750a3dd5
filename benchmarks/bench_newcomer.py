"""A newcomer's first minutes, measured as a newcomer meets them: a fresh `git clone` of this checkout's
HEAD, then the README's two commands, `make repro` and `make test`, each timed as a whole; and the
install alone (`make setup` with an empty uv cache, so every package is fetched, as on a new machine).

Run with `make bench` (or `.venv/bin/python benchmarks/bench_newcomer.py [--skip-test]`). It prints the
date and the machine with the figures, for the README's timings. The clone is thrown away, each
command's output kept in a folder it names; the uv cache of the install is a temporary one.
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import subprocess
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def timed(cmd: list[str], cwd: Path, env: dict[str, str], logs: Path) -> float:
    """Wall time of `cmd`, its whole output kept in `logs` (the clone is thrown away: a failure must
    be diagnosable afterwards); an error naming the log, with its tail, if it fails."""
    log = logs / f"{'-'.join(cmd)}.log"
    t0 = time.perf_counter()
    with log.open("w") as out:
        code = subprocess.run(cmd, cwd=cwd, env=env, stdout=out, stderr=subprocess.STDOUT).returncode
    took = time.perf_counter() - t0
    if code:
        tail = log.read_text(errors="replace")[-3000:]
        raise RuntimeError(f"{' '.join(cmd)} exited {code} (its whole output: {log}):\n{tail}")
    return took


def cpu_model() -> str:
    for line in Path("/proc/cpuinfo").read_text().splitlines():
        if line.startswith("model name"):
            return line.split(":", 1)[1].strip()
    return platform.processor() or "unknown CPU"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--skip-test", action="store_true", help="the install and make repro only")
    args = parser.parse_args(argv)
    head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True)
    print(
        f"newcomer's minutes, {datetime.date.today().isoformat()}, {os.cpu_count()} cores ({cpu_model()}), "
        f"a fresh clone of {head.stdout.strip()}"
    )
    # the caller's venv and settings out of the way: the clone makes and uses its own
    env = {
        k: v
        for k, v in os.environ.items()
        if k not in ("VIRTUAL_ENV", "PYTHONPATH") and not k.startswith("MLFLOW_")
    }
    env["PATH"] = os.pathsep.join(p for p in env["PATH"].split(os.pathsep) if not p.startswith(str(REPO)))
    logs = Path(tempfile.mkdtemp(prefix="bench-newcomer-logs-"))
    print(f"each command's output: {logs}")
    with tempfile.TemporaryDirectory(prefix="bench-newcomer-") as tmp:
        clone, cache = Path(tmp) / "needlecue", Path(tmp) / "uv-cache"
        subprocess.run(["git", "clone", "-q", str(REPO), str(clone)], check=True)
        install = timed(["make", "setup"], clone, {**env, "UV_CACHE_DIR": str(cache)}, logs)
        print(f"install (make setup, empty uv cache): {install:.0f} s")
        repro = timed(["make", "repro"], clone, env, logs)  # the install is done: the pipeline, cold
        print(f"make repro after it (a cold needlecue repro of every stage): {repro:.0f} s")
        if not args.skip_test:
            test = timed(["make", "test"], clone, env, logs)
            print(f"make test: {test:.0f} s ({test / 60:.1f} min)")


if __name__ == "__main__":
    main()
