"""The pairing rule on many draws of a batch that is hard for it (tests/signals/test_pairing.py runs one).

A batch of eight trials of a saturating, lagging, noisy 4-channel tactile sensor pressed by hand
(`tests/signals/fabricate.py`, `fabricate_tactile`): with the right files most align below the quality
gate, so the rule must keep them on evidence, not on quality. Each draw is resampled twice, as the
suite's two tests do on the first draw:
- with every trial's own reference: every trial should be kept;
- with the references of its first and third trials swapped: exactly those two should be set aside
  (nothing wrong is kept), and each should name the other as the trial whose reference it holds.

Run with `.venv/bin/python benchmarks/bench_pairing.py [--draws N]` (about 15 s a draw on one core).
Prints one line per draw (the reasons, where a swapped trial names another) and the totals; exits 1
if a draw sets a right trial aside or keeps a swapped one.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tests.signals.fabricate import (  # noqa: E402
    PARAMS,
    TACTILE,
    statuses,
    swap_references,
    tactile_batch,
    write_ingested,
)

TRIALS = 8
DRAW_STEP = 100  # draw k is the batch of seeds 100 k .. 100 k + 7 (the suite's test: draw 0)


def draw(k: int, folder: Path) -> tuple[bool, bool, bool, str]:
    """Draw k: (every right trial kept, exactly the swapped pair set aside, each naming the other,
    what happened)."""
    trials = tactile_batch(range(DRAW_STEP * k, DRAW_STEP * k + TRIALS))
    right = statuses(write_ingested(folder / "right", "tactile", trials, channels=TACTILE))
    aside = sorted(t for t, r in right.items() if r["status"] != "ok")
    low = sum(float(r["quality"]) < PARAMS.min_quality for r in right.values())
    a, _, b = list(trials)[:3]
    swap_references(trials, a, b)
    swapped = statuses(write_ingested(folder / "swapped", "tactile", trials, channels=TACTILE))
    named = {t: r["status"] for t, r in swapped.items() if r["status"] != "ok"}
    caught = set(named) == {a, b}
    each_other = caught and all(
        f"the reference of trial {other} explains" in named[t] for t, other in ((a, b), (b, a))
    )
    detail = (
        f"{low}/{TRIALS} below the gate; right files set aside: {aside or 'none'}; "
        f"swapped {a}<->{b}, set aside: {sorted(named) or 'none'}"
        + ("" if each_other else "".join(f"\n  {t}: {why}" for t, why in sorted(named.items())))
    )
    return not aside, caught, each_other, detail


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--draws", type=int, default=10, help="how many batches to draw (default 10)")
    args = parser.parse_args()
    kept = caught = named = 0
    times = []
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(args.draws):
            started = time.perf_counter()
            ok_right, ok_swap, ok_named, detail = draw(k, Path(tmp) / f"draw{k}")
            times.append(time.perf_counter() - started)
            kept += ok_right
            caught += ok_swap
            named += ok_named
            seeds = f"{DRAW_STEP * k}..{DRAW_STEP * k + TRIALS - 1}"
            print(f"draw {k} (seeds {seeds}): {detail} ({times[-1]:.1f} s)", flush=True)
    print(
        f"right files, every trial kept: {kept}/{args.draws} draws; swapped files, exactly that pair set "
        f"aside: {caught}/{args.draws}, each naming the other: {named}/{args.draws}; "
        f"median {sorted(times)[len(times) // 2]:.1f} s a draw"
    )
    sys.exit(0 if kept == caught == args.draws else 1)


if __name__ == "__main__":
    main()
