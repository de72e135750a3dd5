"""The pipeline on every member of the simulator's family of rigs (docs/physics.md §11): the figures of
issue 24's targets, one row per member, from one cold `dvc repro` each.

    python benchmarks/bench_family.py [--members default,transimpedance,...] [--no-declare] [--units N]
                                      [--new-rig MEMBER] [--calibration-trials N] [--small] [--keep DIR]

Each member runs in its own copy of this checkout's code, dvc.yaml and params.yaml as they were when
the run started (`snapshot`), with `simulate.rig` set to it (the default layout: three training
units, a new unit with its calibration batch; `--small` for a quick look), every stage but register.
`--no-declare` leaves the circuit out of every batch.yaml; `--new-rig` records the new unit's
batches with another member (a lab whose replacement estimator is built differently);
`--calibration-trials` sets the new unit's calibration insertions per angle
(`simulate.calibration_trials_per_angle`, default one); `--units N` keeps the first N training units
(`--units 1`: the paper's lab, one estimator unit). Printed per member: the champion's mean external
NRMSE on the training units (same unit), on the new unit without and with its calibration and their
ratios to the same-unit figure, the combined cue as a trainee sees it (balanced accuracy within 3 s,
wrong cue at the insertion's end and per frame, coverage) on the same unit and on the new unit
calibrated and not, the inputs the models chose, and the wall time.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import yaml

REPO = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
SMALL = {"train_batches": 2, "trials_per_angle": 2, "heldout_trials_per_angle": 6, "angles_deg": [0, 30, 60]}


CODE = ("dvc.yaml", ".dvcignore", "pipeline", "client")  # what a project is made of, with its params.yaml


def _copy(src: Path, dst: Path, names: tuple[str, ...]) -> None:
    for name in names:
        if (src / name).is_dir():
            shutil.copytree(
                src / name, dst / name, ignore=shutil.ignore_patterns("__pycache__", "*.egg-info")
            )
        else:
            shutil.copy(src / name, dst / name)


def snapshot(work: Path) -> Path:
    """This checkout's pipeline, dvc.yaml and params.yaml as they are now, copied once into `work`:
    every project of a run is made from it, so that editing the checkout while a run goes on (each
    member's cold `dvc repro` takes minutes) changes none of its members."""
    code = work / ".code"
    code.mkdir(parents=True)
    _copy(REPO, code, (*CODE, "params.yaml"))
    return code


def project(root: Path, simulate: dict[str, Any], angles: list[float] | None, code: Path) -> Path:
    """A copy of the `code` snapshot with the simulate section updated, its own DVC repo."""
    root.mkdir(parents=True)
    _copy(code, root, CODE)
    params = yaml.safe_load((code / "params.yaml").read_text())
    params["simulate"].update(simulate)
    if angles is not None:
        params["train"]["angles"] = angles
    (root / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    (root / "data" / "raw").mkdir(parents=True)
    env = dict(os.environ, PATH=f"{BIN}{os.pathsep}{os.environ['PATH']}")
    subprocess.run(["dvc", "init", "--no-scm", "-q"], cwd=root, check=True, env=env)
    return root


def new_unit_of(root: Path, member: str, declare: bool, calibration_trials: int) -> None:
    """The new unit's held-out batches and calibration batch (`calibration_trials` insertions per
    angle), recorded with another design, as a lab would drop them into data/raw (the simulator then
    records none)."""
    sys.path.insert(0, str(root))
    from pipeline.config import SimulateParams
    from pipeline.sim import rig

    params = yaml.safe_load((root / "params.yaml").read_text())["simulate"]
    p = SimulateParams(**{**params, "rig": member, "declare_front_end": declare})
    unit = p.new_units[0]
    raw = root / "data" / "raw"
    for angle in p.angles_deg:
        rig.write_new_batch(
            p, raw, f"lab2-heldout-{int(angle)}deg", (angle,), p.heldout_trials_per_angle, unit
        )
    rig.write_new_batch(p, raw, "lab2-calib", p.angles_deg, calibration_trials, unit, purpose="calibration")
    sys.path.remove(str(root))


def run_member(
    member: str,
    declare: bool,
    new_rig: str | None,
    small: bool,
    work: Path,
    code: Path,
    calibration_trials: int | None,
    units: int | None = None,
) -> dict[str, Any]:
    simulate: dict[str, Any] = {"rig": member, "declare_front_end": declare}
    if units is not None:
        from pipeline.config import SimulateParams

        simulate["units"] = list(SimulateParams().units[:units])
    if calibration_trials is not None:
        simulate["calibration_trials_per_angle"] = calibration_trials
    angles = None
    if small:
        simulate.update(SMALL)
        angles = SMALL["angles_deg"]
    if new_rig:
        simulate["calibration_trials_per_angle"] = 0
    root = project(work / member, simulate, angles, code)
    if new_rig:
        new_unit_of(root, new_rig, declare, 1 if calibration_trials is None else calibration_trials)
        params = yaml.safe_load((root / "params.yaml").read_text())
        new = params["simulate"]["new_units"]
        params["simulate"][
            "new_units"
        ] = []  # the simulator records none: the lab's batches are the new unit's
        (root / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
        assert new
    row = repro_figures(root)
    if "error" in row:
        return {"member": member, **row}
    inputs = json.loads((root / "data" / "predictions" / "inputs.json").read_text())
    chosen = sorted({f"{k}:{r['inputs']['kind']}" for k, by in inputs.items() for r in by.values()})
    return {"member": member, **row, "inputs": chosen}


def repro_figures(root: Path) -> dict[str, Any]:
    """One cold `dvc repro` of the project `root` (every stage but register), and its figures: the
    champion's force on the same unit and a new unit, uncalibrated and calibrated, and the combined cue
    as a trainee sees it per unit group; {"error", "seconds"} if it failed."""
    env = dict(
        os.environ,
        PATH=f"{BIN}{os.pathsep}{os.environ['PATH']}",
        MLFLOW_TRACKING_URI=f"sqlite:///{root / 'mlflow.db'}",
        PYTHONPATH=str(root / "client"),  # the copy's client/ and runtime, not the checkout's
    )
    stages = subprocess.run(
        ["dvc", "stage", "list", "--name-only"], cwd=root, env=env, capture_output=True, text=True, check=True
    ).stdout.split()
    started = time.perf_counter()
    done = subprocess.run(
        ["dvc", "repro", *[s for s in stages if s != "register"]],
        cwd=root,
        env=env,
        capture_output=True,
        text=True,
    )
    seconds = time.perf_counter() - started
    if done.returncode:
        return {"error": (done.stdout + done.stderr)[-2000:], "seconds": seconds}
    from pipeline.metrics.document import read_evaluation

    metrics = read_evaluation(root / "reports" / "evaluation.json")
    champ = metrics.unit_transfer["champion"]
    cues = metrics.cues
    seen = cues.get("lstm") or next(iter(cues.values()), {})  # the combined cue: the same for every kind
    same, uncal, cal = champ.same_unit, champ.new_uncalibrated, champ.new_calibrated
    return {
        "same_unit_pct": same,
        "new_uncalibrated_pct": uncal,
        "new_calibrated_pct": cal,
        "calibrated_ratio": None if not same or cal is None else cal / same,
        "uncalibrated_ratio": None if not same or uncal is None else uncal / same,
        "cues": {
            group: seen[group].model_dump()
            for group in ("same_unit", "new_calibrated", "new_uncalibrated")
            if group in seen
        },
        "seconds": seconds,
    }


def _cue(r: dict[str, Any], group: str) -> str:
    """balanced / wrong at the end / wrong frames / coverage, in percent, of one unit group."""
    c = (r.get("cues") or {}).get(group)
    if not c:
        return "–"
    keys = ("balanced_within_s", "wrong_final", "wrong_frames", "coverage_frames")
    return " / ".join(_f(c.get(k), ".1f") for k in keys)


def _f(x: float | None, spec: str) -> str:
    return "–" if x is None else format(x, spec)


def main() -> None:
    from pipeline.sim.rigs import RIGS

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--members", default=",".join(RIGS))
    ap.add_argument("--no-declare", action="store_true")
    ap.add_argument("--new-rig", default=None)
    ap.add_argument("--calibration-trials", type=int, default=None)
    ap.add_argument("--units", type=int, default=None, help="keep the first N training units")
    ap.add_argument("--small", action="store_true")
    ap.add_argument("--keep", type=Path, default=None, help="keep the projects in this folder")
    args = ap.parse_args()
    work = args.keep or Path(tempfile.mkdtemp(prefix="needlecue-family-"))
    code = snapshot(work)
    rows = []
    for member in args.members.split(","):
        row = run_member(
            member,
            not args.no_declare,
            args.new_rig,
            args.small,
            work,
            code,
            args.calibration_trials,
            args.units,
        )
        rows.append(row)
        print(json.dumps(row), flush=True)
    print()
    print(
        "| member | same unit % | new, uncal. % (×) | new, calibrated % (×) | cues same unit "
        "| cues new, calibrated | cues new, uncalibrated | inputs | s |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    print("| (cues: balanced within 3 s / wrong at the end / wrong frames / coverage, %) | | | | | | | | |")
    for r in rows:
        if "error" in r:
            print(f"| {r['member']} | error | | | | | | | {r['seconds']:.0f} |")
            continue
        print(
            f"| {r['member']} | {_f(r['same_unit_pct'], '.2f')} "
            f"| {_f(r['new_uncalibrated_pct'], '.2f')} ({_f(r['uncalibrated_ratio'], '.2f')}) "
            f"| {_f(r['new_calibrated_pct'], '.2f')} ({_f(r['calibrated_ratio'], '.2f')}) "
            f"| {_cue(r, 'same_unit')} | {_cue(r, 'new_calibrated')} | {_cue(r, 'new_uncalibrated')} "
            f"| {', '.join(r['inputs'])} | {r['seconds']:.0f} |"
        )
    if args.keep is None:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
