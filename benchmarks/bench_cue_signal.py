"""How much angle signal a rig's FSRs carry for the cue estimator: the evidence behind issue 24's cue
figures on the family (docs/units.md, "What a sub-linear FSR costs the cues").

    python benchmarks/bench_cue_signal.py [--variants default,power-law,power-law:law_exponent=1.0]

A variant is a member of the simulator's family (docs/physics.md §11), optionally with fields of its
`Estimator` changed (`member:field=value:field=value`): a counterfactual that is not a member, to see
which part of a design costs the signal. Each variant runs in a fresh copy of this checkout's
pipeline (the variant appended to the copy's `pipeline/sim/rigs.py`) through simulate, ingest,
resample and split on the default layout, then prints, per evidence stage of the angle estimator
(rest reading, then the loading levels 1-9): its leave-one-batch-out accuracy on the training trials
(`pipeline.cues.estimator.fit_angle_estimator`), and the signal-to-scatter ratio of its newest features:
the mean distance between the mean features of adjacent angles over the trials' scatter within one
unit and angle.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]
STAGES = (
    ["simulate", "data/simulated"],
    ["ingest", "data/raw", "data/simulated", "data/interim/ingested", "reports/ingest"],
    ["resample", "data/interim/ingested", "data/interim/resampled", "reports/resample"],
    ["split", "data/interim/resampled", "data/processed"],
)
SHOWN = (0, 3, 6, 9)  # the stages whose signal-to-scatter ratio is printed


def parse(variant: str) -> tuple[str, dict[str, float]]:
    """("power-law", {"law_exponent": 1.0}) of "power-law:law_exponent=1.0"."""
    member, *fields = variant.split(":")
    return member, {k: float(v) for k, v in (f.split("=", 1) for f in fields)}


def project(root: Path, member: str, overrides: dict[str, float]) -> None:
    """A copy of the pipeline whose rig `variant` is `member` with `overrides`, and its params."""
    for package in ("pipeline", "client"):  # the training package; the client's and the runtime's
        shutil.copytree(
            REPO / package, root / package, ignore=shutil.ignore_patterns("__pycache__", "*.egg-info")
        )
    with (root / "pipeline" / "sim" / "rigs.py").open("a") as f:
        f.write(
            "\n\n# bench_cue_signal: the variant under study\n"
            "from dataclasses import replace as _replace  # noqa: E402\n"
            f"RIGS['variant'] = _replace(RIGS[{member!r}], **{overrides!r})\n"
        )
    params = yaml.safe_load((REPO / "params.yaml").read_text())
    params["simulate"]["rig"] = "variant"
    (root / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    (root / "data" / "raw").mkdir(parents=True)


def measure(root: Path) -> dict[str, list[float | None]]:
    """Per stage, the cross-validated accuracy and the signal-to-scatter ratio (run inside the copy)."""
    import numpy as np

    from needlecue_runtime.vocab import channels_of
    from pipeline.config import CuesParams, load_section
    from pipeline.cues.estimator import fit_angle_estimator
    from pipeline.cues.unit_evidence import trial_features
    from pipeline.dataset.splits import SplitFiles

    params = load_section(CuesParams, "cues", root / "params.yaml")
    files = SplitFiles(root / "data" / "processed")
    train, circuits = files.by_angle("train"), files.front_ends()
    estimator = fit_angle_estimator(train, params, None, circuits)
    channels = channels_of(next(iter(train.values())))
    n = len(channels)
    trials, _ = trial_features(train, channels, params, circuits)
    ratios: list[float | None] = []
    for j in range(len(estimator["stages"])):
        between, within = [], []
        for unit in sorted({t.unit for t in trials}):
            means = {}
            for angle in sorted({t.angle for t in trials}):
                mine = [t for t in trials if (t.unit, t.angle) == (unit, angle) and t.stage >= j]
                x = np.array([t.at(j, n)[-n:] for t in mine])
                if len(x) >= 2:
                    means[angle] = x.mean(axis=0)
                    within.append(float(x.std(axis=0, ddof=1).mean()))
            keys = sorted(means)
            between += [float(np.linalg.norm(means[b] - means[a])) for a, b in itertools.pairwise(keys)]
        ratios.append(float(np.mean(between) / np.mean(within)) if between and within else None)
    return {"accuracy": [s["cv_accuracy"] for s in estimator["stages"]], "ratio": ratios}


def run_variant(variant: str, keep: Path | None) -> dict[str, list[float | None]]:
    member, overrides = parse(variant)
    if keep is None:
        root = Path(tempfile.mkdtemp(prefix="bench-cue-signal-"))
    else:
        root = keep / variant.replace(":", "_")
    root.mkdir(parents=True, exist_ok=True)
    try:
        project(root, member, overrides)
        env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(root), str(root / "client")]))
        for stage in STAGES:
            run = [sys.executable, "-m", "pipeline.execution.run", *stage]
            subprocess.run(run, cwd=root, env=env, check=True, capture_output=True)
        out = subprocess.run(
            [sys.executable, str(Path(__file__).resolve()), "--measure", str(root)],
            cwd=root,
            env=env,
            check=True,
            capture_output=True,
            text=True,
        )
        return json.loads(out.stdout.strip().splitlines()[-1])
    finally:
        if keep is None:
            shutil.rmtree(root, ignore_errors=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--variants", default="default,power-law,power-law:law_exponent=1.0")
    ap.add_argument("--keep", type=Path, help="keep each variant's project under this folder")
    ap.add_argument("--measure", type=Path, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.measure is not None:
        sys.path.insert(0, str(args.measure))
        print(json.dumps(measure(args.measure)))
        return
    header = "accuracy per stage (rest, levels 1-9)"
    shown = " ".join(f"{'s/n ' + str(j):>6}" for j in SHOWN)
    print(f"{'variant':<34} {header:<60} {shown} {'wall s':>7}")
    for variant in args.variants.split(","):
        started = time.perf_counter()
        r = run_variant(variant, args.keep)
        acc = " ".join("  n/a" if a is None else f"{a:.2f}" for a in r["accuracy"])
        ratios = " ".join(
            f"{'n/a' if j >= len(r['ratio']) or r['ratio'][j] is None else format(r['ratio'][j], '.2f'):>6}"
            for j in SHOWN
        )
        print(f"{variant:<34} {acc:<60} {ratios} {time.perf_counter() - started:>7.0f}", flush=True)


if __name__ == "__main__":
    main()
