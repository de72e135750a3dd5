"""Per-frame latency of the simulator's client against the bare model, for every angle's champion.

For each `needle-force-<angle>@champion` in the project's MLflow store (`store.tracking_uri()`),
loaded through `ForceClient.from_registry` (fetched into a temp cache), this streams FRAMES samples of
that angle's external trials (data/processed/<angle>/external.parquet, reset at each trial start, after
WARMUP frames) through `client.step` (ONNX forward pass, window ring buffer, cues) and prints p50 and p99
in µs beside:
- the bare ONNX graph: `session.run` on one frame's prepared input (same session options: 1 thread);
- the torch Predictor on one frame (`predict_arrays` on the last `window` samples, last row), from the
  checkpoint in models/<kind>/<angle>/ when it is the registered one;
and the ratio client / bare. The target is p99 ≤ 1 ms per frame (a frame arrives every 33 ms at 30 Hz).
All figures come from this one run, with the garbage collector on (as in a simulator).
"""

from __future__ import annotations

import os
import platform
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pandas as pd

from needlecue_runtime.registry import store

FRAMES = 3000
WARMUP = 300
TARGET_P99_US = 1000.0


def _percentiles(ns: list[int]) -> tuple[float, float]:
    us = np.asarray(ns, dtype=np.float64) / 1e3
    return float(np.percentile(us, 50)), float(np.percentile(us, 99))


def _frames(external: pd.DataFrame, channels: list[str], n: int) -> list[tuple[bool, np.ndarray, float]]:
    """(starts a trial, volts, t_s) for n frames of the external trials in order, cycling if needed."""
    trials = [g.sort_values("t_s") for _, g in external.groupby(["batch_id", "trial_id"], sort=True)]
    out: list[tuple[bool, np.ndarray, float]] = []
    while len(out) < n:
        for trial in trials:
            volts, t = trial[channels].to_numpy(np.float64), trial["t_s"].to_numpy(np.float64)
            out += [(i == 0, volts[i], float(t[i])) for i in range(len(trial))]
    return out[:n]


def _time(fn: Callable[[int], object], n: int, warmup: int) -> list[int]:
    for i in range(warmup):
        fn(i)
    ns = []
    for i in range(warmup, warmup + n):
        start = time.perf_counter_ns()
        fn(i)
        ns.append(time.perf_counter_ns() - start)
    return ns


def _champions(client: object) -> dict[int, str]:
    """{angle: version} of every needle-force-<angle> with a champion alias."""
    found = {}
    for rm in client.search_registered_models(filter_string="name LIKE 'needle-force-%'"):  # type: ignore[attr-defined]
        suffix = rm.name.removeprefix("needle-force-")
        if suffix.isdigit() and store.CHAMPION in (rm.aliases or {}):
            found[int(suffix)] = str(rm.aliases[store.CHAMPION])
    return dict(sorted(found.items()))


def bench_angle(angle: int, uri: str, cache: Path, root: Path) -> dict[str, object] | None:
    import onnxruntime as ort

    from needlecue_client import ForceClient
    from needlecue_runtime.features import rest_reading, unit_inputs
    from pipeline.modelling.checkpoint import CHECKPOINT_FILE, checkpoint_sha256, load_checkpoint
    from pipeline.modelling.inputs import window_index
    from pipeline.modelling.predictor import Predictor

    client = ForceClient.from_registry(angle, tracking_uri=uri, cache_dir=cache, cues_uncalibrated=True)
    ext_file = root / "data" / "processed" / str(angle) / "external.parquet"
    if not ext_file.is_file():
        print(f"  {angle}°: no {ext_file}: skipped")
        return None
    channels = list(client.channels)
    frames = _frames(pd.read_parquet(ext_file), channels, WARMUP + FRAMES)

    def step(i: int) -> object:
        first, volts, t = frames[i]
        if first:
            client.reset()
        return client.step(volts, t)

    client_ns = _time(step, FRAMES, WARMUP)

    # the inputs the client built, prepared up front: what the bare graph sees per frame (the raw
    # windows, their rest readings, volts, and the unit as the client reads it)
    volts = np.stack([v for _, v, _ in frames])
    starts = np.cumsum([f for f, _, _ in frames]) - 1
    start_pos = np.flatnonzero([f for f, _, _ in frames])[starts]
    t = np.array([s for _, _, s in frames])
    rest = rest_reading(volts, starts, t, client.inputs.rest_s)
    windows = window_index(start_pos, client.window)
    names = client.metadata["graph_inputs"]  # the client runs uncalibrated here: the identity unit
    feed = dict(zip(names[2:], (np.ones(1), *unit_inputs(None, None, len(channels))), strict=True))
    x, r = volts[windows], rest[windows]
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = opts.inter_op_num_threads = 1
    session = ort.InferenceSession(
        str(client.model_dir / "model.onnx"), opts, providers=["CPUExecutionProvider"]
    )

    def bare(i: int) -> object:
        return session.run(None, {**feed, names[0]: x[i : i + 1], names[1]: r[i : i + 1]})

    bare_ns = _time(bare, FRAMES, WARMUP)

    torch_ns = None
    ckpt = root / "models" / client.kind / str(angle) / CHECKPOINT_FILE
    if ckpt.is_file():
        checkpoint = load_checkpoint(ckpt)
        if checkpoint_sha256(checkpoint) == client.metadata["checkpoint_sha256"]:
            predictor = Predictor(checkpoint)
            w = client.window

            def torch_frame(i: int) -> object:
                lo = max(start_pos[i], i - w + 1)  # the trial's samples so far, at most a window
                return predictor.predict_arrays(volts[lo : i + 1])[-1]

            torch_ns = _time(torch_frame, FRAMES, WARMUP)
    return {
        "angle": angle,
        "model": client.name,
        "cues": client.has_cues,
        "client": _percentiles(client_ns),
        "bare": _percentiles(bare_ns),
        "torch": None if torch_ns is None else _percentiles(torch_ns),
    }


def main() -> int:
    uri = store.tracking_uri()
    try:
        registry = store.connect(uri)
    except store.RegistryUnreachable as e:
        print(f"{e}\nno registry: run `make repro` first")
        return 1
    champions = _champions(registry)
    if not champions:
        print(f"no needle-force-<angle>@champion in {uri}: run `make repro` first")
        return 1
    import onnxruntime

    cpu = platform.processor() or platform.machine()
    print(
        f"client latency per frame, µs: {FRAMES} frames of each angle's external trials after {WARMUP} "
        f"warm-up; {cpu}, {os.cpu_count()} CPUs, python {sys.version.split()[0]}, "
        f"onnxruntime {onnxruntime.__version__}, 1 thread; store {uri}"
    )
    header = (
        f"{'angle':>5}  {'model':<28} {'cues':<4}  {'client p50':>10} {'p99':>7}  {'bare p50':>8} {'p99':>7}"
        f"  {'torch p50':>9} {'p99':>7}  {'client/bare p50':>15} {'p99':>5}"
    )
    print(header)
    results = []
    with tempfile.TemporaryDirectory(prefix="needlecue-bench-") as cache:
        for angle in champions:
            r = bench_angle(angle, uri, Path(cache), store.project_root())
            if r is None:
                continue
            results.append(r)
            (c50, c99), (b50, b99) = r["client"], r["bare"]  # type: ignore[misc]
            t50, t99 = r["torch"] or (float("nan"), float("nan"))  # type: ignore[misc]
            print(
                f"{angle:>4}°  {r['model']:<28} {'yes' if r['cues'] else 'no':<4}  {c50:>10.1f} {c99:>7.1f}  "
                f"{b50:>8.1f} {b99:>7.1f}  {t50:>9.1f} {t99:>7.1f}  {c50 / b50:>15.2f} {c99 / b99:>5.2f}"
            )
    if not results:
        print("no external data to stream: run `make repro` first")
        return 1
    worst = max(results, key=lambda r: r["client"][1])  # type: ignore[index]
    p99 = worst["client"][1]  # type: ignore[index]
    verdict = "met" if p99 <= TARGET_P99_US else "NOT met"
    where = f"worst p99 {p99:.1f} µs, {worst['angle']}°"
    print(f"target p99 ≤ {TARGET_P99_US:.0f} µs per frame: {verdict} ({where})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
