"""The registered champions through MLflow's own loader against the simulator's client, on the raw
readings of the calibrated new unit's held-out trials (docs/deploy.md).

For every `needle-force-<angle>@champion` in the project's store and every unit calibration in
data/calibration, one external trial of that unit (data/processed/<angle>/external.parquet) is run
sample by sample through `ForceClient` (calibrated) and, as one batch, through
`mlflow.pyfunc.load_model` on the graph's raw inputs: in volts, and as integer 10-bit counts on 5 V
(against the client on those counts' volts: the recorded volts are not all on a 10-bit grid). Prints
the largest difference in N (the target is 1e-5 N) and the pyfunc's time per sample.

Usage: `python benchmarks/bench_deployed.py` after `make repro`.
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd

from needlecue_runtime.registry import store

PER_COUNT = 5.0 / 1023  # a 10-bit ADC on 5 V


def main() -> int:
    import mlflow

    from needlecue_client import ForceClient
    from needlecue_runtime.features import unit_inputs
    from needlecue_runtime.unit_calibration import read_unit, transform_for
    from pipeline.modelling.checkpoint import ModelConfig
    from pipeline.modelling.export import graph_feed

    root = Path(__file__).resolve().parents[1]
    uri = store.tracking_uri()
    mlflow.set_tracking_uri(uri)
    mlflow.set_registry_uri(uri)
    docs = sorted((root / "data" / "calibration").glob("*.json"))
    if not docs:
        print("no unit calibration in data/calibration: run `make repro` first")
        return 1
    worst = 0.0
    for doc_path in docs:
        doc = read_unit(doc_path)
        unit = doc.unit_id
        for angle in [int(a) for a in doc.angles_used]:
            ext = pd.read_parquet(root / "data" / "processed" / str(angle) / "external.parquet")
            ext = ext[ext["unit_id"] == unit]
            if ext.empty:
                continue
            first = ext.iloc[0]
            trial = ext[(ext["batch_id"] == first["batch_id"]) & (ext["trial_id"] == first["trial_id"])]
            trial = trial.sort_values("t_s")
            with tempfile.TemporaryDirectory() as cache:
                client = ForceClient.from_registry(
                    angle, unit_id=unit, cache_dir=Path(cache), tracking_uri=uri
                )
                volts, t = trial[list(client.channels)].to_numpy(), trial["t_s"].to_numpy()
                ours = np.array([client.step(v, float(s)).force_n for v, s in zip(volts, t, strict=True)])
                counts = np.rint(volts / PER_COUNT)
                client.reset(poll=False)
                quantized = zip(counts * PER_COUNT, t, strict=True)
                ours_q = np.array([client.step(v, float(s)).force_n for v, s in quantized])
                transform = transform_for(doc, client.kind, str(angle), client.metadata["checkpoint_sha256"])
                # what graph_feed reads of a checkpoint: the kind, its window (from a full config) and
                # the inputs; the client's metadata has them (n_in is not read)
                config = ModelConfig(kind=client.kind, n_in=len(client.channels), window=client.window)
                checkpoint = {
                    "kind": client.kind,
                    "config": config.to_dict(),
                    "inputs": client.metadata["inputs"],
                }
            fe = doc.circuit
            unit_feed = unit_inputs(transform, fe, len(volts[0]))
            feed = graph_feed(checkpoint, volts, t, np.arange(len(volts)), unit_feed)
            model = mlflow.pyfunc.load_model(f"models:/needle-force-{angle}@champion")
            start = time.perf_counter()
            got = np.asarray(model.predict(feed)["force_n"])
            per_sample_us = (time.perf_counter() - start) / len(volts) * 1e6
            in_counts = graph_feed(checkpoint, counts, t, np.arange(len(counts)), unit_feed)
            in_counts["volts_per_count"] = np.array([PER_COUNT])
            as_counts = np.asarray(model.predict(in_counts)["force_n"])
            diff, diff_counts = float(np.abs(got - ours).max()), float(np.abs(as_counts - ours_q).max())
            worst = max(worst, diff, diff_counts)
            print(
                f"{unit} {angle:>2}°: {client.name}, calibrated {client.calibrated}, {len(volts)} samples: "
                f"max |pyfunc - client| {diff:.1e} N in volts, {diff_counts:.1e} N in counts; "
                f"pyfunc {per_sample_us:.1f} µs a sample in one batch"
            )
    print(f"largest difference: {worst:.1e} N (target 1e-5 N): {'met' if worst <= 1e-5 else 'NOT met'}")
    return 0 if worst <= 1e-5 else 1


if __name__ == "__main__":
    sys.exit(main())
