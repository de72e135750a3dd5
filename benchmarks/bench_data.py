"""Data-half benchmark: ingest + validate + resample throughput, and `dvc repro` wall times.

Run with `make bench` (or `.venv/bin/python benchmarks/bench_data.py`). Prints medians of
repeated runs measured in this one process, on the default simulated data (params.yaml's
`simulate` section): the machine is shared and noisy, so compare figures of one run.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import yaml

from pipeline.config import IngestParams, ResampleParams, SimulateParams, load_section
from pipeline.reporting import ingest as ingest_report
from pipeline.reporting import resample as resample_report
from pipeline.rig import ingest
from pipeline.signals import resample
from pipeline.sim import rig as simulate

REPO = Path(__file__).resolve().parents[1]
REPEATS = 3


def timed(fn: Callable[[], object], repeats: int = REPEATS) -> list[float]:
    """Wall times of `repeats` calls, with the stages' progress lines silenced."""
    times = []
    for _ in range(repeats):
        with contextlib.redirect_stderr(io.StringIO()):
            t0 = time.perf_counter()
            fn()
            times.append(time.perf_counter() - t0)
    return times


def raw_rows(root: Path) -> int:
    """Data rows (not headers) in every CSV of every batch."""
    return sum(sum(1 for _ in p.open()) - 1 for p in root.rglob("*.csv"))


def copy_env(root: Path) -> dict[str, str]:
    """For commands in the project copy `root`: this venv first on PATH (stage commands call
    `python`) and the copy's own MLflow store (never the user's)."""
    return dict(
        os.environ,
        PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}",
        MLFLOW_TRACKING_URI=f"sqlite:///{root / 'mlflow.db'}",
    )


def dvc_out(root: Path, *args: str) -> str:
    """Run dvc in the project copy `root`."""
    return subprocess.run(
        ["dvc", *args], cwd=root, env=copy_env(root), check=True, capture_output=True, text=True
    ).stdout


def dvc(root: Path, *args: str) -> float:
    """Wall time of one dvc command."""
    t0 = time.perf_counter()
    dvc_out(root, *args)
    return time.perf_counter() - t0


def bench_stages(tmp: Path) -> None:
    params = REPO / "params.yaml"
    sim_params = load_section(SimulateParams, "simulate", params)
    sim = tmp / "simulated"
    t_sim = timed(lambda: simulate.run(sim_params, sim), 1)[0]
    rows = raw_rows(sim)
    print(f"simulate (default params): {t_sim:.2f} s, {rows} raw rows")

    ingest_params = load_section(IngestParams, "ingest", params)
    empty_raw = tmp / "raw"
    empty_raw.mkdir()
    out = tmp / "ingested"

    def run_ingest() -> None:
        result = ingest.ingest_batches([empty_raw, sim], out, ingest_params, log=lambda _: None)
        ingest_report.write_reports(result, tmp / "reports-ingest")

    def cold_ingest() -> None:
        shutil.rmtree(out, ignore_errors=True)
        run_ingest()

    t_ingest = timed(cold_ingest)
    t_reuse = timed(run_ingest)
    resample_params = load_section(ResampleParams, "resample", params)
    t_resample = timed(
        lambda: resample_report.write_reports(
            resample.run(out, tmp / "resampled", resample_params),
            tmp / "resampled",
            tmp / "reports-resample",
            resample_params,
        )
    )

    med_i, med_r, med_u = (statistics.median(t) for t in (t_ingest, t_resample, t_reuse))
    print(f"ingest + validate (cold): median {med_i:.2f} s of {REPEATS} -> {rows / med_i:,.0f} raw rows/s")
    print(f"ingest, unchanged (cache): median {med_u:.2f} s -> {med_i / med_u:.0f}x faster than cold")
    print(f"resample: median {med_r:.2f} s of {REPEATS} -> {rows / med_r:,.0f} raw rows/s")
    print(f"ingest + validate + resample: {rows / (med_i + med_r):,.0f} raw rows/s")


def bench_dvc(tmp: Path) -> None:
    root = tmp / "project"
    root.mkdir()
    for name in ("dvc.yaml", "params.yaml", ".dvcignore"):
        if (REPO / name).exists():
            shutil.copy(REPO / name, root / name)
    shutil.copytree(REPO / "pipeline", root / "pipeline", ignore=shutil.ignore_patterns("__pycache__"))
    (root / "data" / "raw").mkdir(parents=True)
    dvc(root, "init", "--no-scm", "-q")
    dvc(root, "config", "core.analytics", "false")
    # The data half of the pipeline: everything up to and including `split`.
    stages = list(yaml.safe_load((root / "dvc.yaml").read_text())["stages"])
    stages = stages[: stages.index("split") + 1]
    cold = dvc(root, "repro", "split")
    noop = timed(lambda: dvc(root, "repro", "split"))
    print(f"dvc repro split, cold ({' -> '.join(stages)}): {cold:.1f} s")
    print(f"dvc repro split, nothing changed: median {statistics.median(noop):.2f} s of {REPEATS}")
    # Then the rest from there, stage by stage, and the whole pipeline doing nothing.
    n_train = sum(name.startswith("train@") for name in stages_all(root))
    parts = {
        f"train x{n_train}": dvc(root, "repro", "--glob", "train@*"),
        **{name: dvc(root, "repro", name) for name in ("predict", "cues", "evaluate", "report", "register")},
    }
    rest = sum(parts.values())
    noop_all = timed(lambda: dvc(root, "repro"))
    print(
        f"dvc repro, the rest: {rest:.1f} s (" + ", ".join(f"{k} {v:.1f} s" for k, v in parts.items()) + ")"
    )
    print(f"dvc repro, whole pipeline cold: {cold + rest:.1f} s")
    # A lab drops one new tissue cast (one angle) and the scheduled retrain follows it.
    t_retrain, report = retrain_after_new_batch(root)
    print(
        f"needlecue retrain after one new batch (15°, 7 trials): {t_retrain:.1f} s = "
        f"{t_retrain / (cold + rest):.2f}x the cold pipeline; stages run: {len(report['stages_run'])} "
        f"({', '.join(report['stages_run'])}); exit {report['exit_code']}"
    )
    print(
        f"dvc repro, whole pipeline, nothing changed: median {statistics.median(noop_all):.2f} s of {REPEATS}"
    )


def retrain_after_new_batch(root: Path) -> tuple[float, dict]:
    """Wall time of `needlecue retrain` after `needlecue simulate-batch` adds one cast; its report."""
    env = copy_env(root)
    cli = [sys.executable, "-m", "pipeline.cli"]
    new_batch = [*cli, "simulate-batch", "data/raw", "bench-cast-1", "--angles", "15", "--trials", "7"]
    subprocess.run(new_batch, cwd=root, env=env, check=True, capture_output=True)
    t0 = time.perf_counter()
    done = subprocess.run([*cli, "retrain"], cwd=root, env=env, capture_output=True, text=True)
    seconds = time.perf_counter() - t0
    if done.returncode not in (2, 3):
        raise RuntimeError(f"needlecue retrain exited {done.returncode}:\n{done.stderr[-3000:]}")
    return seconds, json.loads((root / "reports" / "retrain" / "latest.json").read_text())


def stages_all(root: Path) -> list[str]:
    """Every stage, matrix items expanded, as `dvc stage list` names them."""
    return dvc_out(root, "stage", "list", "--name-only").split()


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        bench_stages(Path(tmp))
    with tempfile.TemporaryDirectory() as tmp:
        bench_dvc(Path(tmp))


if __name__ == "__main__":
    main()
