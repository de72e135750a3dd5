"""Evidence inside a trial: a timestamp step that no sampling rate explains (a clock that jumped) is a
located problem at ingest; honest lost samples, jitter and a host's bursts are not."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from pipeline.config import IngestParams, ResampleParams
from pipeline.rig.check import check_batches
from pipeline.signals.resample import run as resample
from tests.rig.batches import run
from tests.signals.fabricate import Fabricated, fabricate

CHANNELS = ["fsr1", "fsr2", "fsr3"]


def write_rig_log(root: Path, batch_id: str, trials: dict[str, Fabricated]) -> Path:
    """A rig-log/1 batch folder of fabricated trials: 10-bit counts at 30 Hz, host-stamped, and a
    100 Hz reference in N on its own clock."""
    folder = root / batch_id
    folder.mkdir(parents=True)
    (folder / "batch.yaml").write_text(
        f"format: rig-log/1\nbatch_id: {batch_id}\n"
        "sensor: {unit_id: est-1, channels: [fsr1, fsr2, fsr3], units: counts, adc_bits: 10, vref_v: 5.0}\n"
        "reference: {units: N}\n"
    )
    pd.DataFrame({"trial_id": list(trials), "angle_deg": 30, "tissue_point": "p1"}).to_csv(
        folder / "trials.csv", index=False
    )
    for tid, fab in trials.items():
        fsr = pd.DataFrame(
            {"t_ms": fab.t_ms, **{c: fab.counts[:, k].astype(int) for k, c in enumerate(CHANNELS)}}
        )
        fsr.to_csv(folder / f"{tid}.fsr.csv", index=False, float_format="%.3f")
        ref = pd.DataFrame({"t_s": fab.t_s, **{a: fab.force[:, k] for k, a in enumerate(["fx", "fy", "fz"])}})
        ref.to_csv(folder / f"{tid}.ref.csv", index=False, float_format="%.5f")
    return folder


def jumped(fab: Fabricated, line: int, by_s: float, stream: str = "fsr") -> Fabricated:
    """The trial with one stream's clock jumping forward `by_s` at `line` of its file (header line 1)."""
    i = line - 2
    if stream == "fsr":
        t_ms = fab.t_ms.copy()
        t_ms[i:] += by_s * 1e3
        return Fabricated(t_ms, fab.counts, fab.t_s, fab.force, fab.offset_s, fab.bounds)
    t_s = fab.t_s.copy()
    t_s[i:] += by_s
    return Fabricated(fab.t_ms, fab.counts, t_s, fab.force, fab.offset_s, fab.bounds)


def test_an_estimator_clock_jumping_forward_5_s_is_a_located_problem(tmp_path):
    # Given host stamps at 30 Hz whose clock jumps forward 5 s at line 302, beside an honest trial
    root = tmp_path / "raw"
    write_rig_log(root, "jump", {"t01": jumped(fabricate(1, 0.1), 302, 5.0), "t02": fabricate(2, -0.1)})
    # When ingest reads it
    [checked] = check_batches([root], IngestParams())
    # Then that trial is set aside at that file, line and column, naming the stream and the step
    [problem] = checked.problems
    assert Path(problem.file).name == "t01.fsr.csv" and problem.line == 302 and problem.column == "t_ms"
    assert problem.reason.startswith("clock jump in the estimator stream: t_ms steps forward 50")
    assert "times its median interval of 33" in problem.reason
    assert checked.trials_accepted == ["t02"]


@pytest.mark.parametrize(("by_s", "caught"), [(1.0, True), (0.2, True), (0.05, False)])
def test_a_reference_clock_jump_is_named_in_the_reference_stream(tmp_path, by_s, caught):
    # Given a 100 Hz reference whose clock jumps forward at line 1201
    root = tmp_path / "raw"
    write_rig_log(root, "jump", {"t01": jumped(fabricate(3, 0.0), 1201, by_s, "ref")})
    # When ingest reads it
    [checked] = check_batches([root], IngestParams())
    # Then a step over 10 intervals and 0.1 s is a clock jump, at that line; a shorter one is not
    found = [p for p in checked.problems if "clock jump in the reference stream" in p.reason]
    assert bool(found) == caught
    if caught:
        assert (
            Path(found[0].file).name == "t01.ref.csv" and found[0].line == 1201 and found[0].column == "t_s"
        )


def test_a_step_backwards_is_a_located_problem(tmp_path):
    # Given an estimator stream whose clock steps back 0.5 s at line 150
    root = tmp_path / "raw"
    write_rig_log(root, "back", {"t01": jumped(fabricate(4, 0.0), 150, -0.5)})
    # When ingest reads it / Then it is named at that line: time does not increase
    [checked] = check_batches([root], IngestParams())
    hits = [p for p in checked.problems if p.line == 150 and "time does not increase" in p.reason]
    assert hits and hits[0].column == "t_ms" and Path(hits[0].file).name == "t01.fsr.csv"


def bursty(fab: Fabricated, rng: np.random.Generator) -> Fabricated:
    """A real host's serial log: a stall now and then (up to 0.2 s) after which the buffered samples
    arrive within a millisecond or two of each other, then the stamps catch up with the clock."""
    t = fab.t_ms.copy()
    for start in rng.choice(np.arange(20, t.size - 20), 4, replace=False):
        stall = t[start] + rng.uniform(100.0, 200.0)
        k = start
        while k < t.size and t[k] < stall:
            t[k] = stall + (k - start) * 1.0
            k += 1
    t = np.cumsum(np.r_[t[0], np.maximum(np.diff(t), 1.0)])  # in order of arrival, 1 ms apart at least
    return Fabricated(np.round(t, 3), fab.counts, fab.t_s, fab.force, fab.offset_s, fab.bounds)


def test_a_real_like_recording_with_honest_lost_samples_and_jitter_is_kept(tmp_path):
    # Given a batch recorded as a real rig does: 3 % of the samples lost (runs of several among them),
    # 8 ms of jitter, and a host that stalls and then delivers the buffered samples at once
    rng = np.random.default_rng(0)
    trials = {
        f"t{k:02d}": bursty(fabricate(70 + k, 0.05 * k - 0.15, drop_p=0.03, jitter_ms=8.0), rng)
        for k in range(6)
    }
    steps = [np.diff(fab.t_ms).max() / np.median(np.diff(fab.t_ms)) for fab in trials.values()]
    assert max(steps) > 4  # lost runs and stalls of several intervals are in it
    root = tmp_path / "raw"
    write_rig_log(root, "real-like", trials)
    # When it is ingested and resampled
    result = run([root], tmp_path / "ingested")
    resampled = resample(tmp_path / "ingested", tmp_path / "resampled", ResampleParams(), log=lambda _: None)
    # Then every trial is kept, by both stages, unflagged
    assert result.problems == [] and result.accepted == ["real-like"]
    assert [r["status"] for r in resampled.rows] == ["ok"] * 6
    assert not any(r["flag"] for r in resampled.rows)
