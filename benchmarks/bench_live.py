"""Latency of `needlecue live`: from a line arriving on the port to the cue on the trainee's page.

Plays simulated trials through `needlecue emulate-rig` (a pty, the real rate) into the live chain with
the registered champion (run `make repro` first), the page open in Debian's headless Chromium with
?bench=1, which posts back when each state reached the DOM and the next painted frame. Prints p50 and
p99 of: line read -> state published (the chain), line read -> DOM updated (the page's cue), and
line read -> next animation frame (the paint, which waits for the browser's 60 Hz frame).

    python benchmarks/bench_live.py [--angle 30] [--unit est-sim-101] [--trials N] [--dump FILE.csv]

"written to the page" is when the page's SSE thread handed the state to the socket: what needlecue
controls. The rest, to the DOM, is Chromium's (here headless, software-rendered, sharing the two cores
with the emulator and the live process).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from needlecue_client import ForceClient
from pipeline.live.app import LiveOptions, settings_for
from pipeline.live.display import Board, WebDisplay
from pipeline.live.port import run_port
from pipeline.live.session import LiveSession

EXTRA = os.environ.get("BENCH_CHROMIUM_ARGS", "").split()  # more Chromium flags to try


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--angle", type=float, default=30.0)
    ap.add_argument("--unit", default="est-sim-101")
    ap.add_argument("--trials", type=int, default=2)
    ap.add_argument("--dump", type=Path, help="write every state's timings (ms after its line) to this CSV")
    a = ap.parse_args()
    from playwright.sync_api import sync_playwright

    files = sorted(Path("data/simulated").glob(f"sim-heldout-{a.angle:g}deg-{a.unit}/*.fsr.csv"))[: a.trials]
    if not files:
        sys.exit("no simulated trials: run `make repro` first")
    client = ForceClient.from_registry(a.angle, unit_id=a.unit)
    tmp = Path(tempfile.mkdtemp())
    link = tmp / "rig"
    rig = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "pipeline.cli",
            "emulate-rig",
            *map(str, files),
            "--link",
            str(link),
            "--pause",
            "2",
        ],
        stdout=subprocess.DEVNULL,
    )
    while not link.exists():
        time.sleep(0.05)
    board = Board(client.standard_profile)
    web = WebDisplay(board, port=0).start()
    published: dict[int, tuple[float, float]] = {}  # seq -> (line read, published)

    def publish(state: dict) -> None:
        board.publish(state)
        published[state["seq"]] = (state["host_s"], time.time())

    settings, fixed = settings_for(client, LiveOptions(port=str(link)))
    session = LiveSession(client, settings, publish=publish, fixed=fixed)
    stop = threading.Event()
    reader = threading.Thread(
        target=run_port,
        args=(session, str(link), 115200),
        kwargs={"reset_wait_s": 0.5, "should_stop": stop.is_set},
    )
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path="/usr/bin/chromium", args=["--disable-gpu", *EXTRA])
        page = browser.new_page()
        page.goto(web.url + "?bench=1")
        reader.start()
        rig.wait(timeout=600)
        time.sleep(1.5)  # the page posts its renders every second
        stop.set()
        reader.join(timeout=10)
        browser.close()
    web.stop()
    lines = {s: v for s, v in published.items() if v[0] is not None}
    chain = np.array([(pub - read) * 1000 for read, pub in lines.values()])
    wrote = np.array([(w - lines[s][0]) * 1000 for s, w in board.written if s in lines])
    dom = np.array([(d - lines[s][0]) * 1000 for s, d, _ in board.renders if s in lines])
    paint = np.array([(f - lines[s][0]) * 1000 for s, _, f in board.renders if s in lines])
    if a.dump:
        rows = [
            (s, (pub - lines[s][0]) * 1000, (d - lines[s][0]) * 1000, (f - lines[s][0]) * 1000)
            for s, d, f in board.renders
            if s in lines
            for pub in [lines[s][1]]
        ]
        np.savetxt(a.dump, rows, delimiter=",", fmt="%.3f", header="seq,published_ms,dom_ms,paint_ms")
    print(f"bench_live: {len(files)} trial(s), {len(chain)} states, {len(dom)} rendered on the page")
    for name, v in (
        ("line -> state published", chain),
        ("line -> written to the page", wrote),
        ("line -> cue in the page's DOM", dom),
        ("line -> next painted frame", paint),
    ):
        print(f"  {name:<32} p50 {np.percentile(v, 50):6.2f} ms   p99 {np.percentile(v, 99):6.2f} ms")


if __name__ == "__main__":
    main()
