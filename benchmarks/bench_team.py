"""The team stack: champions through the tracking server against the published bucket, one run.

Needs the project's outputs (`make repro`). Starts a throw-away team stack (PostgreSQL, SeaweedFS,
MLflow with basic auth, the publisher) on free loopback ports in a temp folder, registers the project's
models into it as the lab (the register stage's command; the publisher publishes on the webhook), then
measures, each simulator a separate process (forked after one warm-up fetch each way, so that the
figures are the servers' and the fetch's, not one interpreter's GIL nor 50 processes importing Python
packages at once on 2 cores):
1. SIMULATORS simulators fetching `needle-force-30@champion` at once into empty caches, ROUNDS
   rounds, alternating the old path (the tracking server) and the new (the published bucket): p50 and
   p99 of each round and the median over rounds of each, and their ratio;
2. POLLERS simulators polling the published champion every POLL_S seconds for POLL_FOR_S seconds
   (POLL_PROCESSES processes of threads, starts spread over the interval): p50, p99, max, errors;
3. the lab moving the champion MOVES times while one simulator's client polls every POLL_S seconds:
   seconds from the move to the client running the new version (through webhook, publisher, poll);
4. the tracking server stopped: a fresh simulator fetches the champion and its unit's calibration.
The stack is stopped and deleted at the end.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from needlecue_client import ForceClient, fetch, published  # noqa: E402
from needlecue_client.cache import poll_alias  # noqa: E402
from needlecue_runtime.registry import mlflow_env, store  # noqa: E402
from pipeline.team.stack import Stack, free_base_port  # noqa: E402

ROUNDS = 3
SIMULATORS = 50
POLLERS, POLL_PROCESSES, POLL_S, POLL_FOR_S = 500, 20, 2.0, 60.0
MOVES = 3
ANGLE, NAME = 30, "needle-force-30"
REGISTER = [
    sys.executable, "-m", "pipeline.execution.run", "register", "models", "data/processed",
    "data/predictions", "data/calibration", "reports",
]  # fmt: skip


def _pct(times: list[float], q: float) -> float:
    times = sorted(times)
    return times[int(q * (len(times) - 1))]


def _fetcher(start, out, source: str, cache: str) -> None:
    """One simulator process: wait for the start, fetch into its own empty cache, report the seconds.
    Its connections and clients are its own (the parent's bucket clients are forgotten)."""
    published._buckets.clear()
    start.wait()
    t0 = time.perf_counter()
    try:
        fetch(ANGLE, cache_dir=Path(cache), tracking_uri=source)
        out.put(time.perf_counter() - t0)
    except Exception as e:
        out.put(f"{type(e).__name__}: {e}")


def warm(ways: dict[str, str], tmp: Path) -> None:
    """One fetch each way in this process before the simulators fork, so that they start with every
    module imported and S3's service description loaded, as a running simulator has: the figures are
    then the fetch, not Python's imports (50 of those at once on 2 cores take tens of seconds)."""
    for way, source in ways.items():
        fetch(ANGLE, cache_dir=tmp / f"warm-{way.replace(' ', '-')}", tracking_uri=source)
    published._buckets.clear()


def fetch_round(source: str, tmp: Path) -> tuple[list[float], list[str]]:
    """SIMULATORS processes fetching at once from `source`: the seconds of those that succeeded, and
    the errors of those that failed."""
    ctx = mp.get_context("fork")
    start, out = ctx.Barrier(SIMULATORS + 1), ctx.Queue()
    procs = [
        ctx.Process(target=_fetcher, args=(start, out, source, str(tmp / f"sim-{i}")))
        for i in range(SIMULATORS)
    ]
    for p in procs:
        p.start()
    start.wait()
    got = [out.get(timeout=600) for _ in procs]
    for p in procs:
        p.join()
    return [g for g in got if not isinstance(g, str)], [g for g in got if isinstance(g, str)]


def _poller_process(start, out, source: str, threads: int, offset: int) -> None:
    """`threads` simulators in one process, each polling every POLL_S from its own point in the interval."""
    start.wait()
    t_end = time.monotonic() + POLL_FOR_S
    times: list[float] = []
    errors: list[str] = []
    lock = threading.Lock()

    def one(i: int) -> None:
        next_t = time.monotonic() + POLL_S * ((offset + i) % POLLERS) / POLLERS
        while True:
            time.sleep(max(0.0, next_t - time.monotonic()))
            if time.monotonic() >= t_end:
                return
            t0 = time.perf_counter()
            try:
                poll_alias(NAME, store.CHAMPION, source)
                took, error = time.perf_counter() - t0, None
            except Exception as e:
                took, error = time.perf_counter() - t0, f"{type(e).__name__}: {e}"
            with lock:
                times.append(took)
                if error:
                    errors.append(error)
            next_t += POLL_S

    pool = [threading.Thread(target=one, args=(i,)) for i in range(threads)]
    for t in pool:
        t.start()
    for t in pool:
        t.join()
    out.put((times, errors))


def poll_load(source: str) -> None:
    ctx = mp.get_context("fork")
    per = POLLERS // POLL_PROCESSES
    start, out = ctx.Barrier(POLL_PROCESSES + 1), ctx.Queue()
    procs = [
        ctx.Process(target=_poller_process, args=(start, out, source, per, k * per))
        for k in range(POLL_PROCESSES)
    ]
    for p in procs:
        p.start()
    start.wait()
    results = [out.get(timeout=POLL_FOR_S + 300) for _ in procs]
    for p in procs:
        p.join()
    times = [t for r in results for t in r[0]]
    errors = [e for r in results for e in r[1]]
    print(f"polling: {POLLERS} simulators every {POLL_S:g} s for {POLL_FOR_S:g} s ({POLL_PROCESSES} procs): "
          f"{len(times)} polls ({len(times) / POLL_FOR_S:.0f}/s), {len(errors)} errors, "
          f"p50 {1000 * statistics.median(times):.1f} ms, p99 {1000 * _pct(times, 0.99):.1f} ms, "
          f"max {1000 * max(times):.1f} ms")  # fmt: skip
    if errors:
        print(f"  e.g. {errors[0]}")


def moves(stack: Stack, source: str, tmp: Path) -> None:
    """Seconds from the lab moving the champion to a polling client running it."""
    import mlflow

    client = ForceClient.from_registry(ANGLE, cache_dir=tmp / "mover", tracking_uri=source, poll_s=POLL_S)
    took: list[float] = []
    out: list[float] = []  # seconds from the move to the manifest in the bucket
    lab = stack.role_env("lab")
    for _ in range(MOVES):
        env = {
            **{k: v for k, v in lab.items() if k.startswith("MLFLOW_")},
            "MLFLOW_REGISTRY_URI": stack.tracking_uri,
        }
        with mlflow_env.environment(env), store.writing(stack.tracking_uri) as w:
            champion = store.alias_version(w, NAME, store.CHAMPION)
            new = mlflow.register_model(champion.source, NAME, tags=champion.tags)
            w.set_registered_model_alias(NAME, store.CHAMPION, new.version)
        t0 = time.monotonic()
        watch = threading.Thread(target=_watch, args=(source, str(new.version), t0, out), daemon=True)
        watch.start()
        while client.version["version"] != new.version and time.monotonic() - t0 < 120:
            time.sleep(0.05)  # an insertion's end: the client polls if POLL_S has passed
            client.reset()
        took.append(time.monotonic() - t0)
        watch.join(timeout=120)
        if client.version["version"] != new.version:
            raise SystemExit(f"the client did not take v{new.version} within 120 s")
    print(f"champion moved -> running on a client polling every {POLL_S:g} s: "
          f"{', '.join(f'{t:.2f}' for t in took)} s (median {statistics.median(took):.2f} s); "
          f"of which published (webhook, publisher): {', '.join(f'{t:.2f}' for t in out)} s")  # fmt: skip


def _watch(source: str, version: str, t0: float, out: list[float]) -> None:
    """When the bucket's manifest names `version` (asked every 20 ms on connections of its own)."""
    bucket = published.Bucket.at(source)
    while time.monotonic() - t0 < 120:
        found = bucket.manifest(NAME, store.CHAMPION)
        if found is not None and str(found[0]["version"]) == version:
            out.append(time.monotonic() - t0)
            return
        time.sleep(0.02)


def main() -> None:
    if not (ROOT / "models").is_dir():
        raise SystemExit("no trained models: run `make repro` first")
    with tempfile.TemporaryDirectory() as tmp:
        tmp_path = Path(tmp)
        stack = Stack(tmp_path / "stack")
        stack.init(base_port=free_base_port())
        stack.start(progress=lambda _m: None)
        try:
            lab = stack.role_env("lab")
            t0 = time.perf_counter()
            done = subprocess.run(
                [*REGISTER, str(tmp_path / "registry.json")], cwd=ROOT, capture_output=True, text=True,
                env={**os.environ, **lab, "MLFLOW_REGISTRY_URI": lab["MLFLOW_TRACKING_URI"]},
            )  # fmt: skip
            if done.returncode != 0:
                raise SystemExit(f"register failed:\n{done.stdout[-2000:]}\n{done.stderr[-2000:]}")
            print(f"register into the stack: {time.perf_counter() - t0:.1f} s")
            check = [
                sys.executable,
                "-m",
                "pipeline.cli",
                "team",
                "publish",
                "--check",
                "--dir",
                str(stack.dir),
            ]
            t0 = time.perf_counter()
            while subprocess.run(check, cwd=ROOT, capture_output=True).returncode != 0:
                if time.perf_counter() - t0 > 300:
                    raise SystemExit("the publisher did not publish within 300 s")
                time.sleep(1)
            print(f"published by the publisher {time.perf_counter() - t0:.1f} s after register ended")
            os.environ.update(stack.role_env("simulator"))
            published = f"published+{stack.published_url}"
            ways = {"tracking server": stack.tracking_uri, "published bucket": published}
            p50s: dict[str, list[float]] = {w: [] for w in ways}
            p99s: dict[str, list[float]] = {w: [] for w in ways}
            warm(ways, tmp_path)
            for r in range(ROUNDS):
                for way, source in ways.items():
                    times, errors = fetch_round(source, tmp_path / f"r{r}-{way.replace(' ', '-')}")
                    p50s[way].append(statistics.median(times))
                    p99s[way].append(_pct(times, 0.99))
                    p50, p99 = p50s[way][-1], p99s[way][-1]
                    print(f"fetch round {r + 1}, {way}: {SIMULATORS} processes at once, {len(errors)} "
                          f"failed; the others p50 {p50:.3f} s, p99 {p99:.3f} s")  # fmt: skip
                    if errors:
                        print(f"  e.g. {errors[0][:300]}")
            med = {w: (statistics.median(p50s[w]), statistics.median(p99s[w])) for w in ways}
            for way in ways:
                p50, p99 = med[way]
                print(f"fetch, {way}, median of {ROUNDS} rounds: p50 {p50:.3f} s, p99 {p99:.3f} s")
            old, new = med["tracking server"][1], med["published bucket"][1]
            print(f"fetch p99 ratio, published / tracking server: {new / old:.4f} ({old / new:.0f}x faster)")
            poll_load(published)
            moves(stack, published, tmp_path)
            stack.stop_one("mlflow")
            t0 = time.perf_counter()
            client = ForceClient.from_registry(
                15, unit_id="est-sim-101", cache_dir=tmp_path / "down", tracking_uri=published, poll_s=None
            )
            print(f"tracking server stopped: fetched {client.name}, calibrated={client.calibrated} "
                  f"for est-sim-101, in {time.perf_counter() - t0:.2f} s")  # fmt: skip
        finally:
            rounds = [x for x in stack.log("publisher").read_text().splitlines() if f"{NAME}@" in x]
            print("the publisher's last rounds:", *rounds[-MOVES:], sep="\n  ")
            stack.stop(purge=True)


if __name__ == "__main__":
    main()
