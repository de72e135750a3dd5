"""Two revisions of the project side by side: cold `dvc repro` wall time, per-stage times, and
whether they produce the same outputs (metrics.json and every stage output DVC hashes).

    python benchmarks/bench_revisions.py OLD_REV [NEW_REV] [--save-lock PATH]   (NEW_REV: HEAD)

`--save-lock PATH` copies NEW_REV's dvc.lock to PATH: the lock of a fresh clone (cold ingest
cache, fresh MLflow store), which is the one to commit (docs/reproducibility.md).

Each revision runs from a fresh clone in a temp folder with this venv's tools and its own MLflow
store, one after the other in this one process (the machine is shared: compare figures of one run).
Outputs are compared by path: a stage renamed or split between the revisions shows as missing on
one side, which is expected; the bytes of outputs both have must match.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent


def checkout(rev: str, dest: Path) -> Path:
    """A clone of REPO at `rev` (committed work only: a clone is what a user gets)."""
    subprocess.run(["git", "clone", "-q", str(REPO), str(dest)], check=True)
    subprocess.run(["git", "checkout", "-q", rev], cwd=dest, check=True)
    return dest


def repro(root: Path) -> tuple[float, dict[str, float]]:
    """Cold `dvc repro` (outputs and lock removed first): total seconds and seconds per stage group."""
    shutil.rmtree(root / ".dvc" / "cache", ignore_errors=True)
    (root / "dvc.lock").unlink(missing_ok=True)
    env = dict(os.environ, PATH=f"{BIN}{os.pathsep}{os.environ['PATH']}")
    env["MLFLOW_TRACKING_URI"] = f"sqlite:///{root / 'bench-mlflow.db'}"
    proc = subprocess.Popen(
        [str(BIN / "dvc"), "repro"],
        cwd=root,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    assert proc.stdout is not None
    stages: dict[str, float] = {}
    current, t_stage = None, time.perf_counter()
    start = t_stage
    tail: list[str] = []
    for line in proc.stdout:
        tail = [*tail[-30:], line]
        match = re.match(r"Running stage '([^']+)'", line)
        if match:
            now = time.perf_counter()
            if current is not None:
                stages[current] = stages.get(current, 0.0) + now - t_stage
            current, t_stage = match.group(1).split("@")[0], now
    if proc.wait() != 0:
        raise RuntimeError(f"dvc repro failed in {root}:\n{''.join(tail)}")
    end = time.perf_counter()
    if current is not None:
        stages[current] = stages.get(current, 0.0) + end - t_stage
    return end - start, stages


def evaluation(root: Path) -> dict:
    """The full evaluation of a revision (evaluation.json; before it existed, metrics.json held it)."""
    path = root / "reports" / "evaluation.json"
    return json.loads((path if path.is_file() else root / "reports" / "metrics.json").read_text())


def outputs(root: Path) -> dict[str, str]:
    """{output path: md5} of every stage output in dvc.lock."""
    lock = yaml.safe_load((root / "dvc.lock").read_text())["stages"]
    return {o["path"]: o["md5"] for stage in lock.values() for o in stage.get("outs", [])}


def main(old: str, new: str = "HEAD", save_lock: Path | None = None) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        runs = {}
        for label, rev in (("old", old), ("new", new)):
            root = checkout(rev, Path(tmp) / label)
            seconds, stages = repro(root)
            runs[label] = (root, seconds, stages)
            parts = ", ".join(f"{k} {v:.1f} s" for k, v in stages.items())
            print(f"{label} ({rev}): cold dvc repro {seconds:.1f} s ({parts})")
        (old_root, t_old, _), (new_root, t_new, _) = runs["old"], runs["new"]
        print(f"new / old: {t_new / t_old:.2f}x")
        a, b = outputs(old_root), outputs(new_root)
        same = sorted(p for p in a.keys() & b.keys() if a[p] == b[p])
        differ = sorted(p for p in a.keys() & b.keys() if a[p] != b[p])
        print(f"outputs with the same bytes: {len(same)}; differing: {differ or 'none'}")
        only_old, only_new = sorted(a.keys() - b.keys()), sorted(b.keys() - a.keys())
        print(f"only in old: {only_old or 'none'}; only in new: {only_new or 'none'}")
        m_old, m_new = evaluation(old_root), evaluation(new_root)
        print(f"evaluation numbers identical: {m_old == m_new}")
        if save_lock is not None:
            shutil.copy(new_root / "dvc.lock", save_lock)
            print(f"{new}'s dvc.lock saved to {save_lock}")


if __name__ == "__main__":
    args = sys.argv[1:]
    lock_to = None
    if "--save-lock" in args:
        i = args.index("--save-lock")
        lock_to = Path(args[i + 1])
        del args[i : i + 2]
    main(*args[:2], save_lock=lock_to)
