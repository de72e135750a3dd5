"""The warm interpreter (`pipeline/execution/preload.py`): how soon a stage stops when its caller is killed
outright, and what a stage costs to start warm against fresh.

A light server (json preloaded only) serves a stage that ignores SIGTERM and sleeps; the caller is
killed with SIGKILL, and the time until the stage is gone (exited or a zombie) is measured. Then the
same trivial stage is started through the server and with `NEEDLECUE_PRELOAD=0`.

    python benchmarks/bench_preload.py [--runs 5]
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from pipeline.execution import preload

SLEEPER = """import os, signal, sys, time
signal.signal(signal.SIGTERM, signal.SIG_IGN)  # a stage that would not stop on a polite request
open(sys.argv[1], "w").write(str(os.getpid()))
time.sleep(60)
"""
QUICK = "import sys\n"
CALLER = """import os, sys
from pipeline.execution import preload
status = preload.run_stage(sys.argv[1:], dict(os.environ))
sys.exit(98 if status is None else status)
"""


def _gone(pid: int) -> bool:
    stat = Path(f"/proc/{pid}/stat")
    try:
        return stat.read_text().split()[2] == "Z"
    except OSError:
        return True


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=5)
    runs = parser.parse_args().runs
    work = Path(tempfile.mkdtemp(prefix="ncb-", dir="/tmp"))
    root = str(Path(__file__).resolve().parents[1])
    env = dict(os.environ, NEEDLECUE_PRELOAD_DIR=str(work / "s"), NEEDLECUE_PRELOAD_MODULES="json")
    env["PYTHONPATH"] = os.pathsep.join([root, str(work)])
    (work / "sleeper.py").write_text(SLEEPER)
    (work / "quick.py").write_text(QUICK)
    try:
        preload.run_stage(["json.tool", "--help"], env)  # none yet: starts one
        log = preload.socket_path(env)
        assert log is not None
        log = log.with_suffix(".log")
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and not (log.is_file() and "ready" in log.read_text()):
            time.sleep(0.1)
        stops = []
        for k in range(runs):
            pidfile = work / f"pid{k}"
            caller = subprocess.Popen(
                [sys.executable, "-c", CALLER, "sleeper", str(pidfile)], env=env, cwd=work
            )
            while not pidfile.exists():
                time.sleep(0.01)
            time.sleep(0.2)
            stage = int(pidfile.read_text())
            start = time.monotonic()
            caller.kill()
            caller.wait()
            while not _gone(stage):
                time.sleep(0.002)
            stops.append(time.monotonic() - start)
        starts: dict[str, list[float]] = {"warm": [], "fresh": []}
        for _ in range(runs):
            for mode, extra in (("warm", {}), ("fresh", {preload.OFF: "0"})):
                start = time.monotonic()
                done = subprocess.run([sys.executable, "-c", CALLER, "quick"], env={**env, **extra}, cwd=work)
                if mode == "fresh":  # the launcher then runs the stage itself, as pipeline.execution.run does
                    subprocess.run([sys.executable, "-m", "quick"], env=env, cwd=work, check=True)
                else:
                    assert done.returncode == 0, "the server did not take the stage"
                starts[mode].append(time.monotonic() - start)
        print(
            f"stage gone after its caller's SIGKILL: median {statistics.median(stops) * 1e3:.1f} ms "
            f"(max {max(stops) * 1e3:.1f} ms, {runs} runs; it ignores SIGTERM)"
        )
        for mode, times in starts.items():
            print(f"trivial stage, {mode}: median {statistics.median(times) * 1e3:.0f} ms")
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
