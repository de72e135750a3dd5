"""Which of a unit's parts makes a new unit of the independent rig depart from the training layout?
The measurement behind docs/units.md, "A new unit read through a map: measured, not kept" (issue 58).

    python benchmarks/bench_unit_parts.py [--parts none,hysteresis,...] [--seed 7] [--keep DIR]

`benchmarks/independent_rig.py` draws every unit's parts at random (FSR law, hysteresis, connector,
mechanics). Here its new unit `ind-new-1` is made of the training unit's parts (`ind-unit-1`, the
one training unit), with one group of fields taken from the new unit as drawn: a counterfactual per
group. Each case is a fresh copy of this checkout's pipeline with the lab in data/raw, run through
`dvc repro split` only; then the angle estimator is fitted on the training trials (params.yaml's
`cues`) and the new unit's calibration insertions (one per angle) are read as the cues stage reads
them. Printed per case: the evidence stages where the unit departs (`needlecue_runtime.cues.reading.departs`,
"outside what training covered"), and per stage its departure over the distance between
neighbouring angles (`own_departure / neighbour_distance`, above 1: departs).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parent))
import independent_rig
from bench_cue_map import departure_ratios
from bench_family import BIN, project, snapshot

from needlecue_runtime.cues.pack import AngleEstimator
from needlecue_runtime.cues.units import unit_readings
from needlecue_runtime.vocab import CALIBRATION, channels_of
from pipeline.config import CuesParams, load_section
from pipeline.cues.estimator import fit_angle_estimator
from pipeline.cues.unit_evidence import evidence_of, trial_features
from pipeline.dataset.splits import SplitFiles, front_ends

NEW, TRAINING = "ind-new-1", "ind-unit-1"
PARTS: dict[str, tuple[str, ...] | None] = {  # None: every field, the new unit as drawn
    "none": (),
    "connector": ("azimuth_deg",),
    "exponent": ("exponent",),
    "hysteresis": ("hysteresis",),
    "bevel": ("bevel_deg",),
    "gains": ("preload", "r1_kohm", "actuation", "r_i_kohm"),
    "mechanics": ("offset_mm", "axial_share", "moment_share", "radius_mm", "l_tip_mm", "l_cm_mm", "mass_g"),
    "creep-drift": ("creep_g", "creep_tau", "drift"),
    "all": None,
}
DRAW = independent_rig.draw_unit


def draw_with(fields: Sequence[str] | None):
    """`draw_unit` drawing the new unit as the training unit's parts but `fields` (None: all)."""

    def draw(seed: int, unit_id: str) -> independent_rig.Unit:
        drawn = DRAW(seed, unit_id)
        if unit_id != NEW or fields is None:
            return drawn
        base = dataclasses.replace(DRAW(seed, TRAINING), unit_id=NEW)
        return dataclasses.replace(base, **{f: getattr(drawn, f) for f in fields})

    return draw


def departures(root: Path) -> tuple[list[int], list[float]]:
    """(the stages where the new unit departs, its departure over the neighbours' distance per stage)."""
    p = load_section(CuesParams, "cues", root / "params.yaml")
    files = SplitFiles(root / "data" / "processed")
    train = {a: f for a, f in files.by_angle("train").items() if len(f)}
    est = fit_angle_estimator(train, p, None, files.front_ends())
    folder = root / "data" / "processed" / CALIBRATION
    cal = {float(f.stem): pd.read_parquet(f) for f in sorted(folder.glob("*.parquet"))}
    channels = channels_of(next(iter(cal.values())))
    found, _ = trial_features(cal, channels, p, front_ends(folder), est["levels"])
    ev = evidence_of(found, len(channels))[NEW]
    ratios = departure_ratios(est, ev)
    away = [
        j
        for j, r in enumerate(
            unit_readings(AngleEstimator.model_validate(est).stages, est["classes_deg"], ev)
        )
        if r.departs
    ]
    return away, ratios


def run_case(name: str, seed: int, work: Path, code: Path) -> tuple[list[int], list[float]]:
    root = project(work / name, {"enabled": False}, None, code)
    independent_rig.draw_unit = draw_with(PARTS[name])
    try:
        independent_rig.write_lab(root / "data" / "raw", training_units=1, seed=seed, declare=True)
    finally:
        independent_rig.draw_unit = DRAW
    env = dict(os.environ, PATH=f"{BIN}{os.pathsep}{os.environ['PATH']}")
    subprocess.run(["dvc", "repro", "-q", "split"], cwd=root, env=env, check=True, capture_output=True)
    return departures(root)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--parts", default=",".join(PARTS), help=f"of {', '.join(PARTS)}")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--keep", type=Path, default=None)
    args = ap.parse_args()
    names = args.parts.split(",")
    if unknown := [n for n in names if n not in PARTS]:
        ap.error(f"unknown part(s) {unknown}; the parts are {', '.join(PARTS)}")
    work = args.keep or Path(tempfile.mkdtemp(prefix="needlecue-parts-"))
    code = snapshot(work)
    print(
        f"new unit {NEW} made of {TRAINING}'s parts but (departure / neighbours per evidence stage, 0: rest)"
    )
    for name in names:
        started = time.perf_counter()
        away, ratios = run_case(name, args.seed, work, code)
        print(
            f"  {name:<12} departs at {away or 'none'}; "
            + " ".join(f"{r:.1f}" for r in ratios)
            + f"  ({time.perf_counter() - started:.0f} s)",
            flush=True,
        )


if __name__ == "__main__":
    main()
