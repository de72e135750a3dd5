"""Ingest's batch folders and cache: input roots, duplicates, reuse of unchanged batches, crash
safety, and checking folders without writing."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pandas as pd
import pytest

from pipeline.config import IngestParams
from pipeline.rig import batch_store, check, ingest
from tests.helpers import tree_hash
from tests.rig.batches import TRIALS, A, copy_batch, drop_column, run, set_cell

# --------------------------------------------------------------------------- folders and roots


def test_duplicate_batch_id_in_second_root_is_set_aside(raw_dir, lab_bench_a, tmp_path):
    # Given the same batch in the raw and the simulated folder
    sim = tmp_path / "sim"
    shutil.copytree(lab_bench_a, sim / A)
    # When both are ingested
    result = run([raw_dir, sim], tmp_path / "out")
    # Then the raw copy is used and the second is set aside with a Problem naming it
    assert result.accepted == [A]
    dup = [b for b in result.batches if b.action == "duplicate"]
    assert len(dup) == 1 and dup[0].source_dir == sim / A
    assert "already read from" in dup[0].problems[0].reason and dup[0].problems[0].file == str(sim / A)
    assert json.loads((tmp_path / "out" / A / "batch.json").read_text())["source_dir"] == str(raw_dir / A)


def test_batch_folder_with_an_invalid_name_is_set_aside(raw_dir, lab_bench_a, tmp_path):
    # Given a batch folder (and batch_id) with a space in its name
    copy_batch(lab_bench_a, raw_dir, "lab bench")
    # When ingested / Then it is set aside for its id, the other batch goes through
    result = run([raw_dir], tmp_path / "out")
    assert result.accepted == [A] and result.set_aside == ["lab bench"]
    assert "does not match" in result.problems[0].reason


def test_missing_folders_have_no_batches(tmp_path):
    # Given neither input folder exists / When ingested / Then nothing happens, no error
    result = run([tmp_path / "nope", tmp_path / "nada"], tmp_path / "out")
    assert result.batches == [] and list((tmp_path / "out").iterdir()) == []


def test_output_inside_an_input_folder_is_refused(raw_dir):
    # Given an output folder under the raw folder / When ingest starts / Then it refuses
    with pytest.raises(ValueError, match="overlaps"):
        run([raw_dir], raw_dir / "ingested")


# --------------------------------------------------------------------------- incremental


def test_unchanged_batch_is_reused_without_parsing(raw_dir, lab_bench_a, tmp_path, monkeypatch):
    # Given a first ingest
    out = tmp_path / "out"
    first = run([raw_dir], out)
    assert first.parsed == [A]
    stored = tree_hash(out)

    # When it runs again with parsing made impossible
    def no_parse(*_a, **_k):
        raise AssertionError("an unchanged batch was parsed")

    with monkeypatch.context() as m:
        m.setattr(ingest, "parse_batch", no_parse)
        second = run([raw_dir], out)
    # Then the batch is reused and its outputs are untouched
    assert second.reused == [A] and second.parsed == []
    assert second.batches[0].trials_accepted == TRIALS
    assert tree_hash(out) == stored
    # When a second batch arrives, only that one is parsed
    copy_batch(lab_bench_a, raw_dir, "lab-bench-b")
    third = run([raw_dir], out)
    assert third.parsed == ["lab-bench-b"] and third.reused == [A]
    # When a byte of a file changes, that batch is parsed again
    set_cell(raw_dir / "lab-bench-b" / "t001.ref.csv", 5, "fx", "1.5")
    fourth = run([raw_dir], out)
    assert fourth.parsed == ["lab-bench-b"] and fourth.reused == [A]
    # When the ingest params change, everything is parsed again
    assert run([raw_dir], out, IngestParams(min_samples=20)).parsed == [A, "lab-bench-b"]
    # When a batch is removed from the raw folder, its output goes too
    shutil.rmtree(raw_dir / A)
    fifth = run([raw_dir], out, IngestParams(min_samples=20))
    assert fifth.removed == [A] and not (out / A).exists() and fifth.reused == ["lab-bench-b"]


def test_set_aside_batch_is_not_parsed_again_either(raw_dir, tmp_path, monkeypatch):
    # Given a batch set aside for a bad batch.yaml
    (raw_dir / A / "batch.yaml").write_text("format: [\n")
    out = tmp_path / "out"
    assert run([raw_dir], out).set_aside == [A]
    assert sorted(p.name for p in (out / A).iterdir()) == ["fingerprint.json", "problems.json"]
    # When ingest runs again / Then it is reused, problems and all
    monkeypatch.setattr(ingest, "parse_batch", lambda *a, **k: pytest.fail("parsed"))
    again = run([raw_dir], out)
    assert again.reused == [A] and again.set_aside == [A] and "not valid YAML" in again.problems[0].reason


def test_crash_while_writing_leaves_no_matching_fingerprint(raw_dir, tmp_path, monkeypatch):
    # Given an ingested batch that then changes
    out = tmp_path / "out"
    run([raw_dir], out)
    set_cell(raw_dir / A / "t001.fsr.csv", 5, "left", "0.5")
    # When writing its new outputs fails half way
    with monkeypatch.context() as m:
        m.setattr(batch_store, "write_parquet", lambda *a, **k: (_ for _ in ()).throw(OSError("disk full")))
        with pytest.raises(OSError):
            run([raw_dir], out)
    # Then the next run parses it again (no stale fingerprint matches) and writes the new value
    again = run([raw_dir], out)
    assert again.parsed == [A]
    fsr = pd.read_parquet(out / A / "fsr.parquet")
    assert fsr.loc[fsr.trial_id == "t001", "left"].iloc[3] == 0.5
    assert sorted(p.name for p in out.iterdir()) == [A]


def test_a_batch_naming_two_units_beside_one_whose_unit_is_a_list_is_written_not_crashed(
    raw_dir, lab_bench_a, tmp_path
):
    # Given a batch whose trials.csv names two units, beside a batch whose sensor.unit_id is a list
    trials = raw_dir / A / "trials.csv"
    rows = trials.read_text().splitlines()
    units = ["unit_id", "est-bench-01", "est-other", "est-bench-01"]
    trials.write_text("\n".join(f"{r},{u}" for r, u in zip(rows, units, strict=True)) + "\n")
    listed = copy_batch(lab_bench_a, raw_dir, "lab-bench-b")
    meta = listed / "batch.yaml"
    meta.write_text(meta.read_text().replace("unit_id: est-bench-01", "unit_id: [est-bench-01, est-other]"))
    out = tmp_path / "out"
    # When both are ingested
    result = run([raw_dir], out)
    # Then the other unit's trial is set aside at its line, the listed batch as a whole, and every
    # JSON written holds plain values (line numbers are ints)
    assert result.accepted == [A] and result.set_aside == ["lab-bench-b"]
    problems = json.loads((out / A / batch_store.PROBLEMS).read_text())
    assert [(p["trial_id"], p["line"], p["column"]) for p in problems] == [("t002", 3, "unit_id")]
    stored = json.loads((out / A / batch_store.FINGERPRINT).read_text())
    assert stored["outcome"]["trials_set_aside"] == ["t002"]
    listed_problems = json.loads((out / "lab-bench-b" / batch_store.PROBLEMS).read_text())
    assert "sensor.unit_id" in listed_problems[0]["reason"]


def test_a_batch_that_fails_unexpectedly_is_set_aside_and_the_others_go_on(
    raw_dir, lab_bench_a, tmp_path, monkeypatch
):
    # Given two batches, one of which the reader cannot take for a reason no check foresaw
    copy_batch(lab_bench_a, raw_dir, "lab-bench-b")
    real = ingest.parse_batch

    def parse(batch_dir, *args):
        if batch_dir.name == "lab-bench-b":
            raise ValueError("Out of range float values are not JSON compliant: inf")
        return real(batch_dir, *args)

    monkeypatch.setattr(ingest, "parse_batch", parse)
    # When ingested
    result = run([raw_dir], tmp_path / "out")
    # Then that batch is set aside with the error in one line naming its batch.yaml; the other is in
    assert result.accepted == [A] and result.set_aside == ["lab-bench-b"]
    (problem,) = [p for p in result.problems if p.batch_id == "lab-bench-b"]
    assert problem.file == str(raw_dir / "lab-bench-b" / "batch.yaml")
    assert problem.reason.startswith("cannot be ingested: ValueError: Out of range float values")


# --------------------------------------------------------------------------- check


def test_check_folders_reports_problems_and_writes_nothing(raw_dir, lab_bench_a, tmp_path):
    # Given a good fixture and a broken copy
    bad = copy_batch(lab_bench_a, raw_dir, "lab-bench-b")
    drop_column(bad / "t001.fsr.csv", "left")
    before = tree_hash(tmp_path)
    # When they are checked (as a folder of batches and as one batch folder)
    problems = check.check_folders([raw_dir], IngestParams())
    single = check.check_folders([lab_bench_a], IngestParams())
    # Then exactly the broken file is reported, and nothing was written anywhere
    assert [(p.batch_id, Path(p.file).name, p.column) for p in problems] == [
        ("lab-bench-b", "t001.fsr.csv", "left")
    ]
    assert single == []
    assert tree_hash(tmp_path) == before


@pytest.mark.parametrize("how", ["emptied", "missing"])
def test_a_vanished_input_folder_stops_ingest_instead_of_emptying_the_store(raw_dir, tmp_path, how):
    # Given a store ingested from the raw folder, then the folder empty or gone (a share not mounted)
    out = tmp_path / "out"
    run([raw_dir], out)
    stored = tree_hash(out)
    shutil.move(raw_dir, tmp_path / "elsewhere")
    if how == "emptied":
        raw_dir.mkdir()
    # When ingest runs again / Then it stops, naming the folder and the batches, and changes nothing
    with pytest.raises(ValueError, match=rf"input folder {raw_dir} is (empty|missing).*1 batch\(es\).*{A}"):
        run([raw_dir], out)
    assert tree_hash(out) == stored


def test_a_batch_removed_on_purpose_still_leaves_the_store(raw_dir, lab_bench_a, tmp_path):
    # Given a store of two batches, then one batch folder deleted while the other stays
    copy_batch(lab_bench_a, raw_dir, "lab-bench-b")
    out = tmp_path / "out"
    run([raw_dir], out)
    shutil.rmtree(raw_dir / "lab-bench-b")
    # When ingest runs again / Then that batch leaves the store, the other stays
    result = run([raw_dir], out)
    assert result.removed == ["lab-bench-b"] and result.accepted == [A]


def test_a_folder_name_with_a_line_break_is_reported_on_one_line(raw_dir, lab_bench_a, tmp_path):
    # Given a batch folder whose name holds a line break
    copy_batch(lab_bench_a, raw_dir, "lab\nbench")
    logged: list[str] = []
    # When ingested
    result = ingest.ingest_batches([raw_dir], tmp_path / "out", IngestParams(), log=logged.append)
    # Then it is set aside, and every line said of it is one line, the break written as \n
    assert result.set_aside == ["lab\nbench"]
    said = [line for line in logged if "lab\\nbench" in line]
    assert said and all("\n" not in line for line in logged)
    assert all("\n" not in str(p) for p in result.problems)
