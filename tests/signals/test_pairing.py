"""Do a trial's two files record one insertion? Set aside only on evidence: good data from a nonlinear,
noisy, hysteretic sensor, pressed by hand or again and again at a steady pace, is kept (flagged);
swapped files, a reference from another recording and a shifted clock are not, each named."""

from __future__ import annotations

import pandas as pd
import pytest

from pipeline.signals import pairing
from pipeline.signals.resample import process_batch
from tests.signals.fabricate import (
    PARAMS,
    TACTILE,
    Fabricated,
    fabricate,
    fabricate_presses,
    fabricate_tactile,
    statuses,
    swap_references,
    tactile_batch,
    write_ingested,
)


def _shifted(fab: Fabricated, by_s: float) -> Fabricated:
    """The trial with its reference stamped `by_s` later (its clock shifted)."""
    return Fabricated(fab.t_ms, fab.counts, fab.t_s + by_s, fab.force, fab.offset_s, fab.bounds)


def _cuts(first: int, clock: str | None) -> dict[str, Fabricated]:
    """Eight 8 s cuts of one recording of steady presses, 9 s apart in the recording's time; on two
    clocks the reference runs up to 0.2 s behind."""
    return {
        f"c{k}": fabricate_presses(first + k, 0.0 if clock else 0.1 * (k % 5) - 0.2, start_s=9.0 * k)
        for k in range(8)
    }


# These two hold on other draws of the batch too: benchmarks/bench_pairing.py runs them on ten.
def test_a_nonlinear_noisy_sensor_with_the_right_files_keeps_every_trial(tmp_path):
    # Given a batch of a saturating, lagging, noisy 4-channel sensor pressed by hand (not an
    # insertion), every trial with its own reference; most align with a quality below the gate
    trials = tactile_batch(range(8))
    folder = write_ingested(tmp_path, "tactile", trials, channels=TACTILE)
    # When the batch is resampled
    rows = statuses(folder)
    # Then no trial is set aside: their own reference explains them better than any other does
    assert {t: r["status"] for t, r in rows.items()} == dict.fromkeys(trials, "ok")
    low = [r for r in rows.values() if float(r["quality"]) < PARAMS.min_quality]
    assert len(low) >= 4, "the fixture should put most trials below the absolute gate"
    assert all(float(r["peer_quality"]) < float(r["quality"]) * pairing.SWAP_RATIO for r in low)


def test_swapped_reference_files_of_the_same_sensor_are_set_aside_naming_each_other(tmp_path):
    # Given the same kind of batch with the references of two trials swapped
    trials = tactile_batch(range(8))
    a, _, b = list(trials)[:3]
    swap_references(trials, a, b)
    folder = write_ingested(tmp_path, "tactile", trials, channels=TACTILE)
    # When it is resampled
    rows = statuses(folder)
    # Then exactly those two are set aside, each naming the trial whose reference it matches
    aside = {t: r["status"] for t, r in rows.items() if r["status"] != "ok"}
    assert set(aside) == {a, b}
    assert f"the reference of trial {b} explains" in aside[a] and "swapped?" in aside[a]
    assert f"the reference of trial {a} explains" in aside[b]


def test_swapped_insertions_of_the_simulator_like_rig_are_still_set_aside(tmp_path):
    # Given insertion-shaped trials (the FSR tripod) with two references swapped
    trials = {f"a30-t{k:02d}": fabricate(seed=40 + k, offset_s=0.05 * k - 0.15) for k in range(6)}
    swap_references(trials, "a30-t01", "a30-t04")
    folder = write_ingested(tmp_path, "sim-like", trials, channels=["fsr1", "fsr2", "fsr3"])
    rows = statuses(folder)
    # Then those two are set aside as swapped, the rest kept
    assert [t for t, r in rows.items() if r["status"] != "ok"] == ["a30-t01", "a30-t04"]
    assert all("swapped?" in rows[t]["status"] for t in ("a30-t01", "a30-t04"))


def test_a_shared_clock_estimates_no_offset(tmp_path):
    # Given a batch whose two streams were stamped by one clock (no offset between them)
    trials = {f"t{s:03d}": fabricate_tactile(s, 0.0) for s in range(3)}
    folder = write_ingested(tmp_path, "one-clock", trials, channels=TACTILE, clock="shared")
    rows = statuses(folder)
    # Then every trial is aligned at an offset of exactly 0 and kept
    assert all(r["status"] == "ok" and float(r["offset_s"]) == 0.0 for r in rows.values())
    assert all(abs(float(r["error_s"])) == 0.0 for r in rows.values())
    # while the same batch on separate clocks has the sensor's lag estimated as an offset
    folder = write_ingested(tmp_path / "b", "two-clocks", trials, channels=TACTILE)
    assert any(abs(float(r["offset_s"])) > 0.05 for r in statuses(folder).values())


@pytest.mark.parametrize("clock", [None, "shared"])
@pytest.mark.parametrize("first", [0, 50])
def test_steady_presses_of_a_hysteretic_sensor_keep_every_trial_flagged(tmp_path, first, clock):
    # Given cuts of a recording of steady presses: any cut's reference lines up a little with any
    # other's, and every cut aligns below the quality gate (far below on one clock, which leaves
    # the sensor's own lag in)
    trials = _cuts(first, clock)
    folder = write_ingested(tmp_path, "presses", trials, channels=TACTILE, clock=clock)
    # When the batch is resampled
    rows = statuses(folder)
    # Then every trial is kept, and each one below the gate is flagged with why it was kept
    assert {t: r["status"] for t, r in rows.items()} == dict.fromkeys(trials, "ok")
    assert all(float(r["quality"]) < PARAMS.min_quality for r in rows.values())
    assert all("kept: no other trial's reference fits it clearly better" in r["flag"] for r in rows.values())


def test_a_shifted_clock_is_named_as_one(tmp_path):
    # Given three kinds of batch, each with one reference stamped 2 s late: insertions of the
    # simulator-like rig, a hand-pressed tactile sensor, and steady presses said to share one clock
    cases = [
        ("sim-like", {f"a{k}": fabricate(40 + k, 0.05 * k - 0.15) for k in range(6)}, "a1", None),
        ("tactile", {f"t{s}": fabricate_tactile(s, 0.1) for s in range(6)}, "t1", None),
        ("presses", _cuts(0, "shared"), "c2", "shared"),
    ]
    for name, trials, moved, clock in cases:
        trials[moved] = _shifted(trials[moved], 2.0)
        channels = ["fsr1", "fsr2", "fsr3"] if name == "sim-like" else TACTILE
        # When each is resampled
        rows = statuses(write_ingested(tmp_path, name, trials, channels=channels, clock=clock))
        # Then only that trial is set aside, as a shifted clock
        assert [t for t, r in rows.items() if r["status"] != "ok"] == [moved], name
        assert rows[moved]["status"].startswith("set aside: shifted clock: "), name
    # (on one clock by the stamps: "+2.00 s from the estimator at its start and +2.00 s at its end")
    assert "+2.00 s from the estimator at its start and +2.00 s at its end" in rows[moved]["status"]


def test_a_reference_from_another_recording_is_set_aside_for_its_stamps(tmp_path):
    # Given cuts of one recording on one clock, one of them given the reference of a cut of another
    # recording (stamped in that recording's time)
    trials = _cuts(0, "shared")
    other = fabricate_presses(99, 0.0, start_s=200.0)
    c = trials["c3"]
    trials["c3"] = Fabricated(c.t_ms, c.counts, other.t_s, other.force, 0.0, c.bounds)
    # When resampled
    rows = statuses(write_ingested(tmp_path, "presses", trials, channels=TACTILE, clock="shared"))
    # Then it alone is set aside, the stamps of both files named
    assert [t for t, r in rows.items() if r["status"] != "ok"] == ["c3"]
    assert (
        "the estimator is stamped 27.00 to 34.99 s, the reference 200.00 to 207.99 s" in rows["c3"]["status"]
    )
    assert "a reference from another recording?" in rows["c3"]["status"]


def test_judge_keeps_a_trial_its_own_reference_explains_best():
    verdict = pairing.judge(0.3, {"x": 0.05, "y": 0.1, "z": 0.42}, 0.7)
    assert verdict.reason is None and verdict.best_peer == 0.42
    assert verdict.flag is not None and "best of 3: 0.42" in verdict.flag


def test_judge_sets_aside_on_evidence_only():
    swapped = pairing.judge(0.2, {"x": 0.05, "y": 0.8}, 0.7)
    assert (
        swapped.reason is not None and "reference of trial y" in swapped.reason and swapped.best_peer == 0.8
    )
    # no better than unrelated references, or nothing to compare with: kept, flagged
    unrelated = pairing.judge(0.12, {"x": 0.05, "y": 0.1, "z": 0.08}, 0.7)
    assert unrelated.reason is None and unrelated.flag is not None
    alone = pairing.judge(0.5, {}, 0.7)
    assert alone.reason is None and alone.flag is not None and "no other trial" in alone.flag
    # its own reference clearly better outside the window: a shifted clock, unless a peer fits better
    shift = pairing.Shift(offset_s=-2.0, outside=0.8, inside=0.2, window_s=0.5)
    moved = pairing.judge(0.2, {"x": 0.3}, 0.7, shift)
    assert moved.reason is not None and moved.reason.startswith("shifted clock: ")
    assert "swapped?" in str(pairing.judge(0.2, {"x": 0.9}, 0.7, shift).reason)
    assert pairing.judge(0.3, {"x": 0.3}, 0.7, pairing.Shift(-2.0, 0.5, 0.3, 0.5)).reason is None


def test_stamps_on_one_clock_name_a_shift_only_against_a_batch_cut_together():
    together = [((0.0, 8.0), (0.0, 8.0)), ((9.0, 17.0), (9.01, 17.0)), ((18.0, 26.0), (18.0, 25.99))]
    # the batch's files start and end together: a reference displaced alike at both ends is shifted
    assert pairing.stamps_shifted(((27.0, 35.0), (27.4, 35.4)), together) is not None
    assert pairing.stamps_shifted(((27.0, 35.0), (27.02, 35.0)), together) is None  # within tolerance
    assert pairing.stamps_shifted(((27.0, 35.0), (27.4, 38.0)), together) is None  # a longer recording
    assert pairing.stamps_shifted(((27.0, 35.0), (26.0, 36.0)), together) is None  # earlier and later
    # a batch whose reference files run longer than the estimator's: the stamps say nothing
    apart = [((0.0, 8.0), (-1.0, 9.0)), ((9.0, 17.0), (8.0, 18.0)), ((18.0, 26.0), (17.0, 27.0))]
    assert pairing.stamps_shifted(((27.0, 35.0), (29.0, 37.0)), apart) is None


def test_a_copied_estimator_file_is_set_aside_naming_the_trial_it_copies(tmp_path):
    # Given insertions where one trial's estimator file is a copy of another's
    trials = {f"a30-t{k:02d}": fabricate(seed=60 + k, offset_s=0.05 * k - 0.15) for k in range(4)}
    first, third = trials["a30-t00"], trials["a30-t02"]
    trials["a30-t02"] = Fabricated(first.t_ms, first.counts, third.t_s, third.force, 0.0, first.bounds)
    rows = statuses(write_ingested(tmp_path, "copy", trials, channels=["fsr1", "fsr2", "fsr3"]))
    # Then the copy is set aside, naming the trial it copies; the original is kept
    assert [t for t, r in rows.items() if r["status"] != "ok"] == ["a30-t02"]
    assert "the estimator stream of a30-t02 is a30-t00's: the same values" in rows["a30-t02"]["status"]


def test_mutual_swaps_need_both_sides():
    swapped = pairing.Verdict(pairing.swapped("b", 0.9, 0.3), 0.9, swapped_with="b")
    kept = pairing.Verdict(None, 0.9, "flag")
    peers = {"a": {"b": 0.9}, "b": {"a": 0.92}}
    assert pairing.mutual_swaps({"a": swapped, "b": kept}, peers, {"a": 0.3, "b": 0.58}) == [("b", "a")]
    # b's own reference fits it about as well as a's: not a swap from b's side
    assert pairing.mutual_swaps({"a": swapped, "b": kept}, peers, {"a": 0.3, "b": 0.85}) == []


def test_a_poor_fit_far_away_is_no_shift():
    # a sensor so poor that its own reference explains 7 % in the window: 18 % by chance elsewhere is
    # more than twice as much, but explains too little to say where the insertion is
    assert pairing.judge(0.07, {}, 0.7, pairing.Shift(1.0, 0.18, 0.07, 0.5)).reason is None
    assert pairing.judge(0.07, {}, 0.7, pairing.Shift(1.0, 0.6, 0.07, 0.5)).reason is not None


def test_peers_are_the_same_angle_first_then_the_rest_at_most_max_peers():
    angles = {f"t{i:02d}": ("30" if i % 3 == 0 else "45") for i in range(20)}
    peers = pairing.peers_of("t00", angles)
    assert len(peers) == pairing.MAX_PEERS and "t00" not in peers
    assert peers[:6] == ["t03", "t06", "t09", "t12", "t15", "t18"] and peers[6:] == ["t01", "t02"]


def test_every_trial_has_one_row_in_batch_order(tmp_path):
    trials = tactile_batch(range(5))
    swap_references(trials, "t000", "t001")
    folder = write_ingested(tmp_path, "tactile", trials, channels=TACTILE)
    _, table, rows = process_batch(folder, PARAMS)
    assert [r["trial_id"] for r in rows] == sorted(trials)
    kept = [r["trial_id"] for r in rows if r["status"] == "ok"]
    assert sorted(pd.unique(table.column("trial_id").to_numpy(zero_copy_only=False))) == kept


def test_on_one_clock_a_trial_fitting_apart_from_its_batch_is_a_shifted_clock(tmp_path):
    # Given insertions stamped by one clock, one reference whose stamps run 0.4 s behind what it
    # recorded (inside the window; its files still start and end with the estimator's)
    trials = {f"a30-t{k:02d}": fabricate(seed=70 + k, offset_s=0.4 if k == 2 else 0.0) for k in range(5)}
    rows = statuses(
        write_ingested(tmp_path, "one-clock", trials, channels=["fsr1", "fsr2", "fsr3"], clock="shared")
    )
    # Then that trial alone is set aside, as a shifted clock against its batch
    assert [t for t, r in rows.items() if r["status"] != "ok"] == ["a30-t02"]
    assert (
        "shifted clock: reference.clock: shared, yet its reference fits best +0.40 s off"
        in rows["a30-t02"]["status"]
    )


def test_a_lag_every_trial_shares_is_the_sensors_not_a_shift():
    assert pairing.lag_off_the_batch(-0.4, 0.9, 0.2, [0.0, 0.01, -0.01]) is not None
    assert pairing.lag_off_the_batch(0.13, 0.6, 0.25, [0.12, 0.14, 0.15]) is None  # the sensor's lag
    assert pairing.lag_off_the_batch(-0.4, 0.9, 0.2, [0.0]) is None  # nothing to compare with
    assert pairing.lag_off_the_batch(-0.4, 0.9, 0.2, [0.3, -0.3, 0.0]) is None  # the batch disagrees
    assert pairing.lag_off_the_batch(-0.4, 0.35, 0.1, [0.0, 0.01]) is None  # explains too little there


@pytest.mark.parametrize("axes", [("fz",), ("fx", "fz")])
def test_pairing_judges_a_reference_of_one_or_two_axes_on_the_axes_it_records(tmp_path, axes):
    # Given insertions whose reference records only some axes (a one-axis load cell: fz), two of its
    # trials' references swapped
    trials = {f"a30-t{k:02d}": fabricate(seed=40 + k, offset_s=0.05 * k - 0.15) for k in range(6)}
    swap_references(trials, "a30-t01", "a30-t04")
    folder = write_ingested(tmp_path, "load-cell", trials, channels=["fsr1", "fsr2", "fsr3"], axes=axes)
    # When the batch is resampled
    info, table, listed = process_batch(folder, PARAMS)
    rows = {r["trial_id"]: r for r in listed}
    # Then the alignment and the pairing work on those axes: the two are set aside for their pairing,
    # the others aligned to their true offsets, and the table holds only the recorded axes. (One axis
    # tells insertions of one shape apart less well than three: the reason may name another trial's
    # reference, or a shifted clock, rather than the swap's partner.)
    assert info.axes == axes
    assert [t for t, r in rows.items() if r["status"] != "ok"] == ["a30-t01", "a30-t04"]
    assert all(
        ("swapped?" in r["status"]) or ("shifted clock" in r["status"])
        for r in rows.values()
        if r["status"] != "ok"
    )
    assert all(abs(float(r["error_s"])) < 0.02 for r in rows.values() if r["status"] == "ok")
    assert [a for a in ("fx", "fy", "fz") if a in table.column_names] == list(axes)
