"""A one-axis reference against the F/T sensor's three (issue 56): the same simulated rig recorded with
`simulate.reference_axes` [fx, fy, fz] and [fz] (a load cell under the tissue), each through a cold
`dvc repro evaluate`, and the champion's external fz NRMSE per angle side by side.

    python benchmarks/bench_one_axis.py [--members default,transimpedance,...] [--small] [--keep DIR]

Printed per member and angle: the champion (the kind with the lowest mean external NRMSE over the axes
its run recorded) and its fz NRMSE in each run, their ratio (one-axis / three-axis), and, on the
one-axis run's data, a plain least squares on the raw channels (volts and an intercept, fitted on the
training split) with the champion's ratio to it: the figure a lab with a load cell would compare
against first. The two runs differ in more than the targets: the clock alignment and the inputs
choice see only fz in the one-axis run, so its grid and inputs may differ a little.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_family import SMALL, project, snapshot

from needlecue_runtime.vocab import sorted_angles
from pipeline.metrics.scores import nrmse_pct

RUNS = {"three-axis": ["fx", "fy", "fz"], "one-axis": ["fz"]}


def cold_repro(root: Path) -> float:
    """Seconds of one `dvc repro evaluate` in `root` (the venv's dvc)."""
    started = time.perf_counter()
    # the stages' `python` is the venv's, as `make` puts it first on PATH
    env = dict(os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}")
    done = subprocess.run(["dvc", "repro", "evaluate"], cwd=root, capture_output=True, text=True, env=env)
    if done.returncode:
        raise RuntimeError(f"dvc repro in {root} failed:\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}")
    return time.perf_counter() - started


def champion_fz(root: Path) -> dict[str, tuple[str, float]]:
    """{angle: (champion kind, its external fz NRMSE %)} of a reproduced project."""
    doc = json.loads((root / "reports" / "evaluation.json").read_text())
    kinds = doc["unit_transfer"]["champion"]["kinds"]
    return {a: (k, doc["within_angle"][k][a]["fz"]["nrmse_pct"]) for a, k in kinds.items()}


def raw_ls_fz(root: Path, angle: str) -> float:
    """External fz NRMSE % of least squares on the raw channels with an intercept, fitted on the
    angle's training split."""
    folder = root / "data" / "processed" / angle
    train, external = (pd.read_parquet(folder / f"{s}.parquet") for s in ("train", "external"))
    channels = [c for c in train.columns if c.startswith("fsr")]

    def design(frame: pd.DataFrame) -> np.ndarray:
        return np.column_stack([frame[channels].to_numpy(np.float64), np.ones(len(frame))])

    weights, *_ = np.linalg.lstsq(design(train), train["fz"].to_numpy(np.float64), rcond=None)
    return float(nrmse_pct((design(external) @ weights)[:, None], external[["fz"]].to_numpy())[0])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--members", default="default", help="family members, comma-separated")
    parser.add_argument("--small", action="store_true", help="the small rig (a quick look)")
    parser.add_argument("--keep", type=Path, help="keep the projects in this folder")
    args = parser.parse_args()
    work = args.keep or Path(tempfile.mkdtemp(prefix="bench-one-axis-"))
    code = snapshot(work)
    for member in args.members.split(","):
        found: dict[str, dict[str, tuple[str, float]]] = {}
        roots: dict[str, Path] = {}
        for run, axes in RUNS.items():
            simulate = {"rig": member, "reference_axes": axes, **(SMALL if args.small else {})}
            angles = SMALL["angles_deg"] if args.small else None
            roots[run] = project(work / f"{member}-{run}", simulate, angles, code)
            seconds = cold_repro(roots[run])
            found[run] = champion_fz(roots[run])
            print(f"{member} {run}: cold dvc repro evaluate {seconds:.0f} s", flush=True)
        print(f"\n{member}: champion external fz NRMSE %, one-axis / three-axis run; one-axis / raw LS")
        print(f"{'angle':>6} {'3-axis':>14} {'1-axis':>14} {'ratio':>6} {'raw LS':>7} {'ratio':>6}")
        ratios, to_ls = [], []
        for angle in sorted_angles(found["one-axis"]):
            (k3, f3), (k1, f1) = found["three-axis"][angle], found["one-axis"][angle]
            ls = raw_ls_fz(roots["one-axis"], angle)
            ratios.append(f1 / f3)
            to_ls.append(f1 / ls)
            print(f"{angle:>6} {k3:>5} {f3:8.3f} {k1:>5} {f1:8.3f} {f1 / f3:6.2f} {ls:7.3f} {f1 / ls:6.2f}")
        print(
            f"median ratio to three-axis {np.median(ratios):.2f} "
            f"(min {min(ratios):.2f}, max {max(ratios):.2f}); "
            f"median ratio to raw LS {np.median(to_ls):.2f} (max {max(to_ls):.2f})\n",
            flush=True,
        )
    print(f"projects in {work}" if args.keep else "")


if __name__ == "__main__":
    main()
