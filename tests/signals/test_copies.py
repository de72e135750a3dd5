"""A stream that is another trial's is named as such, whatever its stamps and the search window; the
advice a pairing reason gives, followed on the case that produced it, never lets a bad file in; a
trial kept with a low quality is a warning line of the stage."""

from __future__ import annotations

import pytest

from pipeline.config import ResampleParams
from pipeline.signals.resample import process_batch, run
from tests.signals.fabricate import PARAMS, Fabricated, fabricate, write_ingested

FSR = ["fsr1", "fsr2", "fsr3"]


def _batch() -> dict[str, Fabricated]:
    return {f"t{k:02d}": fabricate(seed=80 + k, offset_s=0.05 * k - 0.1) for k in range(1, 5)}


def _rows(folder, params: ResampleParams = PARAMS) -> dict[str, dict]:
    _, _, rows = process_batch(folder, params)
    return {r["trial_id"]: r for r in rows}


def _ref_moved(fab: Fabricated, by_s: float) -> Fabricated:
    return Fabricated(fab.t_ms, fab.counts, fab.t_s + by_s, fab.force, fab.offset_s, fab.bounds)


@pytest.mark.parametrize("max_offset_s", [0.5, 1.5])
def test_a_reference_copied_from_another_trial_and_shifted_1_s_is_named_a_copy(tmp_path, max_offset_s):
    # Given a batch whose t03 reference is t01's, its times shifted by 1 s
    trials = _batch()
    t01, t03 = trials["t01"], trials["t03"]
    trials["t03"] = Fabricated(t03.t_ms, t03.counts, t01.t_s + 1.0, t01.force, 0.0, t03.bounds)
    folder = write_ingested(tmp_path, "copied", trials, channels=FSR)
    # When resampled, with the default window and with it widened as a shifted clock's advice says
    rows = _rows(folder, ResampleParams(max_offset_s=max_offset_s))
    # Then t03 alone is set aside, named a copy of t01's reference (not a shifted clock)
    assert [t for t, r in rows.items() if r["status"] != "ok"] == ["t03"]
    assert rows["t03"]["status"].startswith(
        "set aside: the reference of t03 is t01's: the same values, stamped +1.00 s from it"
    )
    assert "shifted clock" not in rows["t03"]["status"]


def test_an_estimator_stream_copied_from_another_trial_is_named_a_copy(tmp_path):
    # Given a batch whose t04 estimator stream is t02's, stamped 1 s later
    trials = _batch()
    t02, t04 = trials["t02"], trials["t04"]
    trials["t04"] = Fabricated(t02.t_ms + 1000.0, t02.counts, t04.t_s, t04.force, 0.0, t04.bounds)
    rows = _rows(write_ingested(tmp_path, "copied", trials, channels=FSR))
    # Then t04 alone is set aside, naming t02
    assert [t for t, r in rows.items() if r["status"] != "ok"] == ["t04"]
    assert "the estimator stream of t04 is t02's: the same values, stamped +1.00 s" in rows["t04"]["status"]


def test_a_shifted_clock_whose_advice_is_followed_is_kept_at_the_right_offset(tmp_path):
    # Given a batch whose t02 reference is its own, stamped 1 s late: a shifted clock
    trials = _batch()
    trials["t02"] = _ref_moved(trials["t02"], 1.0)
    folder = write_ingested(tmp_path, "shifted", trials, channels=FSR)
    rows = _rows(folder)
    assert rows["t02"]["status"].startswith("set aside: shifted clock: its own reference fits best at")
    assert rows["t02"]["status"].endswith("fix the stamps or widen resample.max_offset_s")
    # When the window is widened as advised / Then it is kept, at its true offset less the 1 s
    widened = _rows(folder, ResampleParams(max_offset_s=1.5))["t02"]
    assert widened["status"] == "ok" and not widened["flag"]
    assert abs(float(widened["offset_s"]) - (trials["t02"].offset_s - 1.0)) < 1 / 30
    # When instead its stamps are fixed / Then it is kept at its true offset
    trials["t02"] = _ref_moved(trials["t02"], -1.0)
    fixed = _rows(write_ingested(tmp_path / "fixed", "shifted", trials, channels=FSR))["t02"]
    assert fixed["status"] == "ok" and abs(float(fixed["error_s"])) < 1 / 30


def test_on_one_clock_fixing_the_stamps_is_the_advice_and_it_keeps_the_trial(tmp_path):
    # Given insertions stamped by one clock, t02's reference stamped 2 s late (its ends displaced
    # alike, where the batch's other files start and end together)
    trials = {f"t{k:02d}": fabricate(seed=90 + k, offset_s=0.0) for k in range(1, 6)}
    trials["t02"] = _ref_moved(trials["t02"], 2.0)
    folder = write_ingested(tmp_path, "one-clock", trials, channels=FSR, clock="shared")
    rows = _rows(folder)
    assert rows["t02"]["status"].startswith("set aside: shifted clock: reference.clock: shared")
    assert rows["t02"]["status"].endswith("fix the stamps")
    # When the window is widened anyway / Then it stays set aside (one clock searches no offset)
    widened = _rows(folder, ResampleParams(max_offset_s=2.5))["t02"]["status"]
    assert widened.startswith("set aside: shifted clock: reference.clock: shared")
    # When its stamps are fixed as advised / Then every trial is kept, at 0 s
    trials["t02"] = _ref_moved(trials["t02"], -2.0)
    fixed = _rows(write_ingested(tmp_path / "fixed", "one-clock", trials, channels=FSR, clock="shared"))
    assert all(r["status"] == "ok" and not r["flag"] for r in fixed.values())


def test_on_one_clock_a_lag_off_the_batch_fixed_as_advised_is_kept(tmp_path):
    # Given insertions on one clock, t02's reference stamped 0.4 s behind what it recorded
    trials = {f"t{k:02d}": fabricate(seed=70 + k, offset_s=0.4 if k == 2 else 0.0) for k in range(5)}
    rows = _rows(write_ingested(tmp_path, "one-clock", trials, channels=FSR, clock="shared"))
    assert "fits best +0.40 s off" in rows["t02"]["status"] and rows["t02"]["status"].endswith(
        "fix the stamps"
    )
    # When its stamps are fixed as advised (0.4 s later) / Then every trial is kept
    trials["t02"] = Fabricated(
        *(lambda f: (f.t_ms, f.counts, f.t_s + 0.4, f.force, 0.0, f.bounds))(trials["t02"])
    )
    fixed = _rows(write_ingested(tmp_path / "fixed", "one-clock", trials, channels=FSR, clock="shared"))
    assert all(r["status"] == "ok" for r in fixed.values())


def test_a_kept_trial_with_a_low_quality_and_no_batch_is_a_warning_line(tmp_path):
    # Given an ingested batch of one trial whose estimator clock jumps 5 s at its 301st sample (as if
    # ingest had not looked): 30 Hz host stamps, its later samples paired with the wrong force
    fab = fabricate(seed=5, offset_s=0.1)
    t_ms = fab.t_ms.copy()
    t_ms[300:] += 5000.0
    trials = {"t01": Fabricated(t_ms, fab.counts, fab.t_s, fab.force, fab.offset_s, fab.bounds)}
    write_ingested(tmp_path / "in", "alone", trials, channels=FSR)
    # When the stage runs
    said: list[str] = []
    rows = run(tmp_path / "in", tmp_path / "out", PARAMS, log=said.append).rows
    # Then the trial kept with a flag is a warning line of its own, naming it and its quality
    assert rows[0]["status"] == "ok" and rows[0]["flag"]
    warnings = [s for s in said if s.startswith("resample: warning: ")]
    assert warnings == [
        f"resample: warning: alone/t01 kept with alignment quality {float(rows[0]['quality']):.2f} "
        f"(no other trial of its batch is kept): {rows[0]['flag']}"
    ]
