"""The pipeline on a rig nobody tuned it on: `benchmarks/independent_rig.py` (physics written apart from
the built-in simulator, from the published facts only) as a lab's own rig logs, one cold `dvc repro`
(every stage but register) per case.

    python benchmarks/bench_independent.py [--units 1,3] [--declare yes,no] [--seed 7] [--keep DIR]

Each case is a fresh copy of this checkout's code, dvc.yaml and params.yaml with the simulator off
(`simulate.enabled: false`) and the independent lab in data/raw: `--units` training units on three
tissue casts, the first unit's and a new unit's held-out casts, and the new unit's calibration batch
(one insertion per angle), the circuit declared in batch.yaml or not. Printed per case, as
`bench_family.py` prints them: the champion's force on the same unit and the new unit, uncalibrated
and calibrated, and the combined cue as a trainee sees it.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_family import _cue, _f, project, repro_figures, snapshot
from independent_rig import write_lab


def run_case(units: int, declare: bool, seed: int, work: Path, code: Path) -> dict:
    """One cold `dvc repro` of the independent lab (`units` training units) made from the `code`
    snapshot, and its figures."""
    name = f"u{units}-{'declared' if declare else 'undeclared'}"
    root = project(work / name, {"enabled": False}, None, code)
    write_lab(root / "data" / "raw", training_units=units, seed=seed, declare=declare)
    case = f"{units} unit(s), circuit {'declared' if declare else 'not declared'}"
    return {"case": case, **repro_figures(root)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--units", default="1,3")
    ap.add_argument("--declare", default="yes,no")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--keep", type=Path, default=None)
    args = ap.parse_args()
    work = args.keep or Path(tempfile.mkdtemp(prefix="needlecue-independent-"))
    code = snapshot(work)
    rows = []
    for units in (int(u) for u in args.units.split(",")):
        for declare in (d == "yes" for d in args.declare.split(",")):
            row = run_case(units, declare, args.seed, work, code)
            rows.append(row)
            print(json.dumps(row), flush=True)
    print()
    print(
        "| case | same unit % | new, uncal. % | new, calibrated % (×) | cues same unit "
        "| cues new, calibrated "
        "| cues new, uncalibrated | s |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        if "error" in r:
            print(f"| {r['case']} | error | | | | | | {r['seconds']:.0f} |")
            continue
        print(
            f"| {r['case']} | {_f(r['same_unit_pct'], '.2f')} | {_f(r['new_uncalibrated_pct'], '.2f')} "
            f"| {_f(r['new_calibrated_pct'], '.2f')} ({_f(r['calibrated_ratio'], '.2f')}) "
            f"| {_cue(r, 'same_unit')} | {_cue(r, 'new_calibrated')} | {_cue(r, 'new_uncalibrated')} "
            f"| {r['seconds']:.0f} |"
        )
    if args.keep is None:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
