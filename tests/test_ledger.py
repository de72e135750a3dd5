"""The ledger: every trial of every batch, used where or set aside at which stage and why."""

from __future__ import annotations

from typing import Any

from pipeline import ledger

SRC = "data/raw"


def records() -> dict[str, Any]:
    """Each stage's record for a small lab: batch `cast` (4 trials, 15° and 60°), a second copy of
    it under another folder, a batch whose trials.csv could not be read, and a calibration batch."""
    batches = [
        {
            "batch_id": "cast",
            "source_dir": f"{SRC}/cast",
            "accepted": True,
            "trials_accepted": ["t1", "t2", "t3", "t5"],
            "trials_set_aside": ["t4"],
        },
        {
            "batch_id": "cast",
            "source_dir": "data/other/cast",
            "accepted": False,
            "duplicate": True,
            "trials_accepted": [],
            "trials_set_aside": [],
        },
        {"batch_id": "broken", "source_dir": f"{SRC}/broken", "accepted": False, "trials_accepted": []},
        {
            "batch_id": "calib",
            "source_dir": f"{SRC}/calib",
            "accepted": True,
            "trials_accepted": ["c1", "c2"],
            "trials_set_aside": [],
        },
    ]

    def problem(batch: str, trial: str | None, file: str, reason: str, **at: Any) -> dict[str, Any]:
        return {"batch_id": batch, "trial_id": trial, "file": file, "reason": reason, **at}

    quarantine = [
        problem("cast", "t4", f"{SRC}/cast/t4.fsr.csv", "a0 is not a number", line=7, column="a0"),
        problem("cast", None, "data/other/cast", "batch_id 'cast' was already read from data/raw/cast"),
        problem("broken", None, f"{SRC}/broken/trials.csv", "not UTF-8 (cp1252?)", line=3),
        problem("cast", "t9", f"{SRC}/cast/t9.ref.csv", "no row for trial 't9' in trials.csv: not ingested"),
    ]
    offsets = [
        {"batch_id": "cast", "trial_id": "t1", "angle_deg": "15", "status": "ok"},
        {
            "batch_id": "cast",
            "trial_id": "t2",
            "angle_deg": "15",
            "status": "set aside: reference stream is constant",
        },
        {"batch_id": "cast", "trial_id": "t3", "angle_deg": "15", "status": "ok"},
        {"batch_id": "cast", "trial_id": "t5", "angle_deg": "60", "status": "ok"},
        {"batch_id": "calib", "trial_id": "c1", "angle_deg": "15", "status": "ok"},
        {"batch_id": "calib", "trial_id": "c2", "angle_deg": "15", "status": "ok"},
    ]
    manifest = {
        "angles": {
            "15": {"splits": {"train": [{"batch_id": "cast", "trial_id": "t1"}], "external": []}},
            "60": {"splits": {"external": [{"batch_id": "cast", "trial_id": "t5"}]}},
        },
        "set_aside": [{"batch_id": "cast", "trial_id": "t3", "angle": "15", "reason": "channels differ"}],
        "calibration": {
            "15": [
                {"batch_id": "calib", "trial_id": "c1", "unit_id": "u9"},
                {"batch_id": "calib", "trial_id": "c2", "unit_id": "u9"},
            ]
        },
    }
    calibrations = [
        {
            "unit_id": "u9",
            "trials": [{"batch_id": "calib", "trial_id": "c1", "angle": "15"}],
            "set_aside": [
                {
                    "batch_id": "calib",
                    "trial_id": "c2",
                    "file": "calib/c2.fsr.csv",
                    "angle": "15",
                    "reason": "too short",
                }
            ],
        }
    ]
    return dict(
        batches=batches, quarantine=quarantine, offsets=offsets, manifest=manifest, calibrations=calibrations
    )


def test_every_trial_gets_the_place_the_last_stage_gave_it() -> None:
    # given: every stage's record of a small lab, models trained at 15° only
    # when: the ledger is built
    entries = ledger.build(**records(), trained=[15])
    places = {(e.batch_id, e.trial_id, e.source): e for e in entries}
    # then: a trial used in training, one scored at an angle without models (said so), one calibrating
    t1, t5, c1 = (
        places["cast", "t1", f"{SRC}/cast"],
        places["cast", "t5", f"{SRC}/cast"],
        places["calib", "c1", f"{SRC}/calib"],
    )
    assert (t1.outcome, t1.stage, t1.angle, t1.use) == ("used", "split", "15", "train")
    assert (t5.outcome, t5.use, t5.angle) == ("used", "external", "60") and "60° (train.angles)" in (
        t5.note or ""
    )
    assert (c1.outcome, c1.use, c1.unit_id) == ("used", "calibration", "u9")
    # and each set-aside trial names the stage that refused it, where and why
    aside = {
        (e.batch_id, e.trial_id, e.source): (e.stage, [(w.file, w.line, w.column, w.reason) for w in e.where])
        for e in entries
        if e.outcome == "set aside"
    }
    assert aside == {
        ("cast", "t4", f"{SRC}/cast"): (
            "ingest",
            [(f"{SRC}/cast/t4.fsr.csv", 7, "a0", "a0 is not a number")],
        ),
        ("cast", "t2", f"{SRC}/cast"): (
            "resample",
            [(f"{SRC}/cast/t2.*", None, None, "reference stream is constant")],
        ),
        ("cast", "t3", f"{SRC}/cast"): ("split", [(f"{SRC}/cast/t3.*", None, None, "channels differ")]),
        ("calib", "c2", f"{SRC}/calib"): ("calibrate", [("calib/c2.fsr.csv", None, None, "too short")]),
        # the second copy of `cast` is a batch of its own, with its own folder, not the first copy's trials
        ("cast", None, "data/other/cast"): (
            "ingest",
            [("data/other/cast", None, None, "batch_id 'cast' was already read from data/raw/cast")],
        ),
        ("broken", None, f"{SRC}/broken"): (
            "ingest",
            [(f"{SRC}/broken/trials.csv", 3, None, "not UTF-8 (cp1252?)")],
        ),
        # a stream file without a trial row is on the record too
        ("cast", "t9", f"{SRC}/cast/t9.ref.csv"): (
            "ingest",
            [(f"{SRC}/cast/t9.ref.csv", None, None, "no row for trial 't9' in trials.csv: not ingested")],
        ),
    }
    # and every problem ingest found is carried by exactly one entry
    carried = [w for e in entries for w in e.where if e.stage == "ingest"]
    assert len(carried) == len(records()["quarantine"])


def test_counts_and_the_written_document() -> None:
    # given: the ledger of the small lab
    doc = ledger.document(ledger.build(**records(), trained=[15, 60]))
    # then: trials counted once each, by use and by the stage that set them aside
    c = doc["counts"]
    assert c["trials"] == 8 and c["used"] == 3 and c["set_aside"] == 5
    assert c["used_by_split"] == {"calibration": 1, "external": 1, "train": 1}
    assert c["set_aside_by_stage"] == {"ingest": 2, "resample": 1, "split": 1, "calibrate": 1}
    assert c["batches_set_aside_whole"] == ["broken (data/raw/broken)", "cast (data/other/cast)"]
    # and with models at 60° the external trial there carries no note
    t5 = next(e for e in doc["entries"] if e.get("trial_id") == "t5")
    assert "note" not in t5 and doc["format"] == "needlecue-ledger/1"
    # and of_batches picks one batch's entries
    assert {e.get("trial_id") for e in ledger.of_batches(doc, ["calib"])} == {"c1", "c2"}


def test_a_trial_ingest_accepted_that_no_later_record_holds_is_set_aside_not_lost() -> None:
    # given: ingest accepted a trial, but resample's record has no row for it
    r = records()
    r["offsets"] = [o for o in r["offsets"] if o["trial_id"] != "t1"]
    # when
    entries = ledger.build(**r, trained=[15])
    # then: it is on the record, set aside at resample, with that said
    t1 = next(e for e in entries if e.trial_id == "t1")
    assert (t1.outcome, t1.stage) == ("set aside", "resample")
    assert "resample has no row" in t1.where[0].reason


def test_a_trial_kept_with_a_low_alignment_quality_is_used_and_flagged() -> None:
    from pipeline.reporting.ledger import markdown

    # given: resample kept t1 but flagged it (a low alignment quality, nothing showing its files disagree)
    r = records()
    flag = "alignment quality 0.31 below resample.min_quality = 0.7; kept: no other trial in its batch"
    r["offsets"] = [{**o, "flag": flag} if o["trial_id"] == "t1" else o for o in r["offsets"]]
    # when: the ledger is built and written
    doc = ledger.document(ledger.build(**r, trained=[15]))
    # then: t1 is used, with the flag, counted, and listed for people
    t1 = next(e for e in doc["entries"] if e.get("trial_id") == "t1")
    assert (t1["outcome"], t1["use"], t1["flag"]) == ("used", "train", flag)
    assert doc["counts"]["flagged"] == 1
    assert f"## Used, flagged (1)\n\n- `cast/t1`: {flag}" in markdown(doc)


def test_a_used_trial_whose_force_axes_its_angle_leaves_out_says_which() -> None:
    # given: split kept 15° on the axes every batch there records, leaving out cast's fx and fy, and
    # calib's fy at the calibration of 15°
    r = records()
    r["manifest"]["angles"]["15"]["axes"] = ["fz"]
    r["manifest"]["angles"]["15"]["axes_left_out"] = {"cast": ["fx", "fy"]}
    r["manifest"]["calibration_axes_left_out"] = {"15": {"calib": ["fy"]}}
    # when: the ledger is built
    places = {(e.batch_id, e.trial_id): e for e in ledger.build(**r, trained=[15])}
    # then: the used trials say which of their reference's axes the models at their angle do not use
    assert places[("cast", "t1")].outcome == ledger.USED
    assert places[("cast", "t1")].note == (
        "its reference's fx, fy not used: the models at 15° do not estimate them (not every batch there "
        "records them)"
    )
    assert places[("cast", "t1")].unused_axes == ("fx", "fy")
    assert places[("calib", "c1")].note is not None and "fy not used" in places[("calib", "c1")].note
    written = {
        (e["batch_id"], e.get("trial_id")): e for e in ledger.document(list(places.values()))["entries"]
    }
    assert list(written[("cast", "t1")]["unused_axes"]) == ["fx", "fy"]
    assert "unused_axes" not in written[("cast", "t5")]  # nothing left out at 60°: nothing written
    # and: a trial at an angle that left nothing out carries no such note
    assert places[("cast", "t5")].note is None or "not used" not in places[("cast", "t5")].note
