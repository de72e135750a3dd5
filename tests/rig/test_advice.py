"""The advice an ingest reason gives, followed on the case that produced it, gives the right outcome:
the files pass and nothing wrong is let in."""

from __future__ import annotations

import gzip
from pathlib import Path

import pandas as pd

from pipeline.config import IngestParams
from pipeline.rig.check import check_batches
from tests.rig.batches import TRIALS, A, copy_batch, lines_of, replace_in, write_lines


def _check(root: Path):
    return {c.batch_id: c for c in check_batches([root], IngestParams())}


def test_record_each_insertion_as_its_own_trial(raw_dir):
    # Given a batch whose programme takes 1.5 s an insertion (limit 9 s), and a 10 s trial t001
    b = raw_dir / A
    replace_in(b / "batch.yaml", "insertion_time_s: 5.0", "insertion_time_s: 1.0")
    for t in ("t002", "t003"):
        (b / f"{t}.fsr.csv").unlink(), (b / f"{t}.ref.csv").unlink()
    write_lines(b / "trials.csv", lines_of(b / "trials.csv")[:2])
    assert "the recording lasts" in _check(raw_dir)[A].problems[0].reason
    # When each half is recorded as its own trial, as the reason advises
    for stream, col, per_s in (("fsr.csv", "t_ms", 1000.0), ("ref.csv", "t_s", 1.0)):
        frame = pd.read_csv(b / f"t001.{stream}")
        cut = frame[col].iloc[0] + 5.0 * per_s
        frame[frame[col] < cut].to_csv(b / f"t101.{stream}", index=False)
        frame[frame[col] >= cut].to_csv(b / f"t102.{stream}", index=False)
        (b / f"t001.{stream}").unlink()
    write_lines(b / "trials.csv", [lines_of(b / "trials.csv")[0], "t101,P1,30,0", "t102,P1,30,0"])
    # Then no trial is too long
    checked = _check(raw_dir)[A]
    assert not [p for p in checked.problems if "the recording lasts" in p.reason]


def test_put_each_units_trials_in_a_batch_of_its_own(raw_dir, lab_bench_a):
    # Given a trials.csv whose t003 names another unit
    b = raw_dir / A
    rows = lines_of(b / "trials.csv")
    write_lines(
        b / "trials.csv",
        [rows[0] + ",unit_id", *(r + ",est-bench-01" for r in rows[1:3]), rows[3] + ",est-bench-02"],
    )
    assert _check(raw_dir)[A].trials_set_aside == ["t003"]
    # When its trial goes to a batch of that unit, as advised
    other = copy_batch(b, raw_dir, "lab-bench-b")
    replace_in(other / "batch.yaml", "unit_id: est-bench-01", "unit_id: est-bench-02")
    write_lines(other / "trials.csv", [lines_of(b / "trials.csv")[0], lines_of(b / "trials.csv")[3]])
    for t in ("t001", "t002"):
        (other / f"{t}.fsr.csv").unlink(), (other / f"{t}.ref.csv").unlink()
    write_lines(b / "trials.csv", lines_of(b / "trials.csv")[:3])
    (b / "t003.fsr.csv").unlink(), (b / "t003.ref.csv").unlink()
    # Then every trial passes, each in its unit's batch
    checked = _check(raw_dir)
    assert checked[A].trials_accepted == ["t001", "t002"] and checked["lab-bench-b"].trials_accepted == [
        "t003"
    ]
    assert not checked[A].problems and not checked["lab-bench-b"].problems


def test_keep_one_of_two_forms(raw_dir):
    # Given t002's reference as CSV and as gzip
    b = raw_dir / A
    (b / "t002.ref.csv.gz").write_bytes(gzip.compress((b / "t002.ref.csv").read_bytes()))
    assert "both exist: keep one of them" in _check(raw_dir)[A].problems[0].reason
    # When one of them is kept / Then every trial passes
    (b / "t002.ref.csv").unlink()
    checked = _check(raw_dir)[A]
    assert not checked.problems and checked.trials_accepted == TRIALS


def test_save_it_as_utf8(raw_dir):
    # Given a reference saved as Windows-1252
    ref = raw_dir / A / "t002.ref.csv"
    text = ref.read_text()
    ref.write_bytes(text.replace("t_s,", "t_s_µ,", 1).encode("cp1252"))
    assert "save it as UTF-8" in _check(raw_dir)[A].problems[0].reason
    # When it is saved as UTF-8 (its header as rig-log/1 says) / Then every trial passes
    ref.write_text(text, encoding="utf-8")
    checked = _check(raw_dir)[A]
    assert not checked.problems and checked.trials_accepted == TRIALS


def test_rename_a_reserved_channel(raw_dir):
    # Given a channel named like one of ingest's own columns
    b = raw_dir / A
    replace_in(b / "batch.yaml", "channels: [left, right, top, bottom]", "channels: [left, right, top, line]")
    for t in TRIALS:
        replace_in(b / f"{t}.fsr.csv", "bottom", "line")
    assert "rename the channel" in _check(raw_dir)[A].problems[0].reason
    # When it is renamed, in batch.yaml and the files / Then every trial passes, with that channel
    replace_in(b / "batch.yaml", "line]", "lower]")
    for t in TRIALS:
        replace_in(b / f"{t}.fsr.csv", ",line", ",lower")
    checked = _check(raw_dir)[A]
    assert not checked.problems and checked.trials_accepted == TRIALS
