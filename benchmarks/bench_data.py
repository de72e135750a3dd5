"""Data-half benchmark: ingest + validate + resample throughput (the pipeline's `dvc repro` wall
times: benchmarks/bench_pipeline.py).

Run with `make bench` (or `.venv/bin/python benchmarks/bench_data.py`). Prints medians of
repeated runs measured in this one process, on the default simulated data (params.yaml's
`simulate` section): the machine is shared and noisy, so compare figures of one run.
"""

from __future__ import annotations

import contextlib
import io
import shutil
import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

from pipeline.config import IngestParams, ResampleParams, SimulateParams, load_section
from pipeline.execution.workers import WORKERS
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
        roots = [empty_raw, sim]
        result = ingest.ingest_batches(roots, out, ingest_params, log=lambda _: None, workers=WORKERS)
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


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        bench_stages(Path(tmp))


if __name__ == "__main__":
    main()
