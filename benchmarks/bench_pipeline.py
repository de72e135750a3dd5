"""The pipeline's wall times: a cold `dvc repro` on the defaults stage by stage, its total per stage
kind and per model kind, a no-op `dvc repro`, the scheduled retrain after one new tissue cast, and a
cold `needlecue repro` (the same stages side by side on every core, `pipeline/execution/repro.py`).

Run with `make bench` (or `.venv/bin/python benchmarks/bench_pipeline.py [--fresh]`). Everything runs
in a throw-away copy of the project (code, dvc.yaml, params.yaml), with its own MLflow store. A
stage's time is the wall time from DVC's "Running stage" line to the next one (DVC's own work for the
stage included). `--fresh` also runs the cold pipeline with every stage in a fresh interpreter
(`NEEDLECUE_PRELOAD=0`, pipeline/execution/preload.py), beside the default, in the same run.
"""

from __future__ import annotations

import argparse
import io
import json
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

from pipeline.execution import repro
from pipeline.execution.workers import usable_cpus

REPO = Path(__file__).resolve().parents[1]

REPEATS = 3
STAGE_LINE = re.compile(r"^Running stage '([^']+)'")


def make_copy(root: Path) -> Path:
    """A project copy at `root` with its own DVC repo (no cache, no lock: everything runs)."""
    root.mkdir(parents=True)
    for name in ("dvc.yaml", "params.yaml", ".dvcignore"):
        if (REPO / name).exists():
            shutil.copy(REPO / name, root / name)
    for package in ("pipeline", "client"):  # the training package; the client's and the runtime's
        shutil.copytree(
            REPO / package, root / package, ignore=shutil.ignore_patterns("__pycache__", "*.egg-info")
        )
    (root / "data" / "raw").mkdir(parents=True)
    dvc(root, {}, "init", "--no-scm", "-q")
    dvc(root, {}, "config", "core.analytics", "false")
    return root


def env_of(root: Path, extra: dict[str, str]) -> dict[str, str]:
    """This venv first on PATH (stage commands call `python`), the copy's own MLflow store and its own
    client/ (the venv's editable install is the checkout's)."""
    return dict(
        os.environ,
        PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}",
        MLFLOW_TRACKING_URI=f"sqlite:///{root / 'mlflow.db'}",
        PYTHONPATH=str(root / "client"),
        **extra,
    )


def dvc(root: Path, extra: dict[str, str], *args: str) -> float:
    """Wall time of one dvc command in `root` (its output discarded; an error raised with it)."""
    t0 = time.perf_counter()
    done = subprocess.run(["dvc", *args], cwd=root, env=env_of(root, extra), capture_output=True, text=True)
    if done.returncode:
        raise RuntimeError(f"dvc {' '.join(args)} failed:\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}")
    return time.perf_counter() - t0


def timed_run(
    cmd: list[str], root: Path, extra: dict[str, str], ok: tuple[int, ...] = (0,)
) -> tuple[float, dict[str, float]]:
    """Total wall time of `cmd` (which runs `dvc repro`) and each stage's share (DVC's "Running stage"
    line to the next); an error with its output's tail if it exits with a code not in `ok`."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(
        cmd, cwd=root, env=env_of(root, extra), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
    )
    stages: dict[str, float] = {}
    current, since, tail = None, t0, []
    assert proc.stdout is not None
    for line in proc.stdout:
        tail = [*tail[-40:], line]
        if found := STAGE_LINE.match(line.strip()):
            now = time.perf_counter()
            if current is not None:
                stages[current] = now - since
            current, since = found.group(1), now
    code = proc.wait()
    end = time.perf_counter()
    if current is not None:
        stages[current] = end - since
    if code not in ok:
        raise RuntimeError(f"{' '.join(cmd)} exited {code}:\n" + "".join(tail))
    return end - t0, stages


def timed_repro(root: Path, extra: dict[str, str]) -> tuple[float, dict[str, float]]:
    """Total wall time of `dvc repro` and each stage's share."""
    return timed_run(["dvc", "repro"], root, extra)


def by_group(stages: dict[str, float]) -> dict[str, float]:
    """Stage times summed by stage name without its matrix item (`train`, `choose`), and the train
    stages also by model kind (`train ls`, ...)."""
    out: dict[str, float] = defaultdict(float)
    for name, seconds in stages.items():
        base, _, item = name.partition("@")
        out[base] += seconds
        if base == "train":
            out[f"train {item.rsplit('-', 1)[-1]}"] += seconds
    return dict(out)


def retrain_after_new_batch(root: Path) -> tuple[float, dict[str, float], dict]:
    """Wall time of `needlecue retrain` after `needlecue simulate-batch` adds one cast, each stage's
    share of it, and its report."""
    env = env_of(root, {})
    cli = [sys.executable, "-m", "pipeline.cli"]
    new_batch = [*cli, "simulate-batch", "data/raw", "bench-cast-1", "--angles", "15", "--trials", "7"]
    subprocess.run(new_batch, cwd=root, env=env, check=True, capture_output=True)
    seconds, stages = timed_run([*cli, "retrain"], root, {}, ok=(2, 3))  # retrained (3: some set aside)
    return seconds, stages, json.loads((root / "reports" / "retrain" / "latest.json").read_text())


def print_cold(label: str, total: float, stages: dict[str, float]) -> None:
    print(f"cold dvc repro ({label}): {total:.1f} s, {len(stages)} stages")
    print_groups(stages)


def print_groups(stages: dict[str, float]) -> None:
    """Each stage kind's time, longest first, then the training's per model kind."""
    groups = by_group(stages)
    for name, seconds in sorted(groups.items(), key=lambda kv: -kv[1]):
        if not name.startswith("train "):
            n = sum(1 for s in stages if s.partition("@")[0] == name)
            print(f"  {name:<10} {seconds:7.1f} s" + (f"  ({n} stages)" if n > 1 else ""))
    kinds = {k: v for k, v in groups.items() if k.startswith("train ")}
    print("  training per model kind: " + ", ".join(f"{k[6:]} {v:.1f} s" for k, v in kinds.items()))


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--fresh", action="store_true", help="also a cold run with NEEDLECUE_PRELOAD=0")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        root = make_copy(Path(tmp) / "project")
        total, stages = timed_repro(root, {})
        print_cold("stages in a warm interpreter, the default", total, stages)
        noop = [dvc(root, {}, "repro") for _ in range(REPEATS)]
        print(f"no-op dvc repro: median {statistics.median(noop):.2f} s of {REPEATS}")
        t_retrain, retrain_stages, report = retrain_after_new_batch(root)
        print(
            f"needlecue retrain after one new cast (15°, 7 trials): {t_retrain:.1f} s = "
            f"{t_retrain / total:.2f}x the cold pipeline; {len(report['stages_run'])} stages run; "
            f"exit {report['exit_code']}"
        )
        in_stages = sum(retrain_stages.values())
        print(f"  before its first stage {t_retrain - in_stages:.1f} s; its stages (the last to its exit):")
        for name, seconds in sorted(retrain_stages.items(), key=lambda kv: -kv[1]):
            print(f"  {name:<16} {seconds:7.1f} s")
    with tempfile.TemporaryDirectory() as tmp:
        root = make_copy(Path(tmp) / "project")
        jobs = usable_cpus()
        t0 = time.perf_counter()
        outcome = repro.reproduce(root, repro.dvc_plan(root), jobs, out=io.StringIO(), env=env_of(root, {}))
        parallel = time.perf_counter() - t0
        if outcome.code:
            raise RuntimeError(f"needlecue repro failed at {outcome.failed}:\n" + "\n".join(outcome.tail))
        spans = {name: end - start for name, (start, end) in outcome.spans.items()}
        print(
            f"cold needlecue repro ({jobs} jobs): {parallel:.1f} s = {parallel / total:.2f}x the cold "
            f"dvc repro; {sum(spans.values()):.1f} s of stages side by side"
        )
        print_groups(spans)
    if args.fresh:
        with tempfile.TemporaryDirectory() as tmp:
            root = make_copy(Path(tmp) / "project")
            fresh_total, fresh_stages = timed_repro(root, {"NEEDLECUE_PRELOAD": "0"})
            print_cold("every stage a fresh interpreter, NEEDLECUE_PRELOAD=0", fresh_total, fresh_stages)
            print(f"warm / fresh: {total / fresh_total:.2f}")


if __name__ == "__main__":
    main()
