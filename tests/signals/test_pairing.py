"""Do a trial's two files record one insertion? A low alignment quality is judged against the batch's
other references: good data from a nonlinear, noisy sensor is kept; swapped files are not."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from pipeline.signals import pairing
from pipeline.signals.resample import process_batch
from tests.signals.fabricate import PARAMS, Fabricated, fabricate, fabricate_tactile, write_ingested

TACTILE = ["left", "right", "top", "bottom"]


def _tactile_batch(seeds: range) -> dict[str, Fabricated]:
    # offsets within ±0.2 s: the sensor's own lag (creep, backlash) adds up to about 0.2 s
    return {
        f"t{s:03d}": fabricate_tactile(s, float(np.random.default_rng(s).uniform(-0.2, 0.2))) for s in seeds
    }


def _swap_references(trials: dict[str, Fabricated], a: str, b: str) -> None:
    ta, tb = trials[a], trials[b]
    trials[a] = Fabricated(ta.t_ms, ta.counts, tb.t_s, tb.force, tb.offset_s, ta.bounds)
    trials[b] = Fabricated(tb.t_ms, tb.counts, ta.t_s, ta.force, ta.offset_s, tb.bounds)


def _statuses(folder) -> dict[str, dict]:
    _, _, rows = process_batch(folder, PARAMS)
    return {r["trial_id"]: r for r in rows}


@pytest.mark.parametrize("first", [0, 300])
def test_a_nonlinear_noisy_sensor_with_the_right_files_keeps_every_trial(tmp_path, first):
    # Given a batch of a saturating, lagging, noisy 4-channel sensor pressed by hand (not an
    # insertion), every trial with its own reference; most align with a quality below the gate
    trials = _tactile_batch(range(first, first + 8))
    folder = write_ingested(tmp_path, "tactile", trials, channels=TACTILE)
    # When the batch is resampled
    rows = _statuses(folder)
    # Then no trial is set aside: their own reference explains them better than any other does
    assert {t: r["status"] for t, r in rows.items()} == dict.fromkeys(trials, "ok")
    low = [r for r in rows.values() if float(r["quality"]) < PARAMS.min_quality]
    assert len(low) >= 4, "the fixture should put most trials below the absolute gate"
    assert all(float(r["peer_quality"]) < float(r["quality"]) * pairing.SWAP_RATIO for r in low)


@pytest.mark.parametrize("first", [0, 300])
def test_swapped_reference_files_of_the_same_sensor_are_set_aside_naming_each_other(tmp_path, first):
    # Given the same kind of batch with the references of two trials swapped
    trials = _tactile_batch(range(first, first + 8))
    a, _, b = list(trials)[:3]
    _swap_references(trials, a, b)
    folder = write_ingested(tmp_path, "tactile", trials, channels=TACTILE)
    # When it is resampled
    rows = _statuses(folder)
    # Then exactly those two are set aside, each naming the trial whose reference it matches
    aside = {t: r["status"] for t, r in rows.items() if r["status"] != "ok"}
    assert set(aside) == {a, b}
    assert f"the reference of trial {b} explains" in aside[a] and "swapped?" in aside[a]
    assert f"the reference of trial {a} explains" in aside[b]


def test_swapped_insertions_of_the_simulator_like_rig_are_still_set_aside(tmp_path):
    # Given insertion-shaped trials (the FSR tripod) with two references swapped
    trials = {f"a30-t{k:02d}": fabricate(seed=40 + k, offset_s=0.05 * k - 0.15) for k in range(6)}
    _swap_references(trials, "a30-t01", "a30-t04")
    folder = write_ingested(tmp_path, "sim-like", trials, channels=["fsr1", "fsr2", "fsr3"])
    rows = _statuses(folder)
    # Then those two are set aside as swapped, the rest kept
    assert [t for t, r in rows.items() if r["status"] != "ok"] == ["a30-t01", "a30-t04"]
    assert all("swapped?" in rows[t]["status"] for t in ("a30-t01", "a30-t04"))


def test_a_shared_clock_estimates_no_offset(tmp_path):
    # Given a batch whose two streams were stamped by one clock (no offset between them)
    trials = {f"t{s:03d}": fabricate_tactile(s, 0.0) for s in range(3)}
    folder = write_ingested(tmp_path, "one-clock", trials, channels=TACTILE, clock="shared")
    rows = _statuses(folder)
    # Then every trial is aligned at an offset of exactly 0 and kept
    assert all(r["status"] == "ok" and float(r["offset_s"]) == 0.0 for r in rows.values())
    assert all(abs(float(r["error_s"])) == 0.0 for r in rows.values())
    # while the same batch on separate clocks has the sensor's lag estimated as an offset
    folder = write_ingested(tmp_path / "b", "two-clocks", trials, channels=TACTILE)
    assert any(abs(float(r["offset_s"])) > 0.05 for r in _statuses(folder).values())


def test_judge_keeps_a_trial_its_own_reference_explains_best():
    assert pairing.judge(0.3, {"x": 0.05, "y": 0.1, "z": 0.42}, 0.7) == pairing.Verdict(None, 0.42)


def test_judge_names_the_swap_and_refuses_a_reference_no_better_than_unrelated_ones():
    swapped = pairing.judge(0.2, {"x": 0.05, "y": 0.8}, 0.7)
    assert (
        swapped.reason is not None and "reference of trial y" in swapped.reason and swapped.best_peer == 0.8
    )
    unrelated = pairing.judge(0.12, {"x": 0.05, "y": 0.1, "z": 0.08}, 0.7)
    assert unrelated.reason is not None and "no better than other trials' references" in unrelated.reason
    alone = pairing.judge(0.5, {}, 0.7)
    assert alone.reason is not None and "no other trial" in alone.reason and alone.best_peer is None


def test_peers_are_the_same_angle_first_then_the_rest_at_most_max_peers():
    angles = {f"t{i:02d}": ("30" if i % 3 == 0 else "45") for i in range(20)}
    peers = pairing.peers_of("t00", angles)
    assert len(peers) == pairing.MAX_PEERS and "t00" not in peers
    assert peers[:6] == ["t03", "t06", "t09", "t12", "t15", "t18"] and peers[6:] == ["t01", "t02"]


def test_every_trial_has_one_row_in_batch_order(tmp_path):
    trials = _tactile_batch(range(5))
    _swap_references(trials, "t000", "t001")
    folder = write_ingested(tmp_path, "tactile", trials, channels=TACTILE)
    _, table, rows = process_batch(folder, PARAMS)
    assert [r["trial_id"] for r in rows] == sorted(trials)
    kept = [r["trial_id"] for r in rows if r["status"] == "ok"]
    assert sorted(pd.unique(table.column("trial_id").to_numpy(zero_copy_only=False))) == kept
