"""The ledger stage's entry point: reads the stages' records, writes ledger.json and ledger.md, and
stops with one clear line on a malformed record."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest
import typer

from pipeline.stages import ledger
from tests.test_ledger import records


def write_records(root: Path) -> list[Path]:
    """The small lab's records as the stages write them; returns the stage's input paths."""
    r = records()
    root.mkdir(parents=True, exist_ok=True)
    paths = [root / n for n in ("batches.json", "quarantine.json", "offsets.csv", "manifest.json")]
    paths[0].write_text(json.dumps(r["batches"]))
    paths[1].write_text(json.dumps(r["quarantine"]))
    with paths[2].open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=["batch_id", "trial_id", "angle_deg", "status"])
        w.writeheader()
        w.writerows(r["offsets"])
    paths[3].write_text(json.dumps(r["manifest"]))
    cal = root / "calibration"
    cal.mkdir()
    for doc in r["calibrations"]:
        (cal / f"{doc['unit_id']}.json").write_text(json.dumps(doc))
    return [*paths, cal]


def test_stage_writes_the_ledger_and_its_markdown(tmp_path, capsys):
    # given: the stages' records and params training 15° and 60°
    inputs = write_records(tmp_path / "in")
    (tmp_path / "params.yaml").write_text("train:\n  angles: [15, 60]\n")
    # when: the stage runs
    ledger.main(*inputs, tmp_path / "out", tmp_path / "params.yaml")
    # then: ledger.json accounts for every trial, and ledger.md names each one set aside with its place
    doc = json.loads((tmp_path / "out" / "ledger.json").read_text())
    assert doc["counts"]["trials"] == 8 and doc["counts"]["set_aside"] == 5
    md = (tmp_path / "out" / "ledger.md").read_text()
    assert "| 15° | 1 | 0 | 0 | 0 | 1 |" in md
    assert (
        "`cast/t4` (data/raw/cast): set aside at ingest: data/raw/cast/t4.fsr.csv:7 (a0): a0 is not a number"
        in md
    )
    assert "ledger: 8 trials: 3 used, 5 set aside" in capsys.readouterr().err


def test_a_malformed_record_stops_the_stage_with_one_line(tmp_path, capsys):
    # given: a manifest that is not a JSON object
    inputs = write_records(tmp_path / "in")
    inputs[3].write_text("[]")
    (tmp_path / "params.yaml").write_text("train:\n  angles: [15]\n")
    # when / then: exit 1, one line naming the file
    with pytest.raises(typer.Exit) as stopped:
        ledger.main(*inputs, tmp_path / "out", tmp_path / "params.yaml")
    assert stopped.value.exit_code == 1
    err = capsys.readouterr().err.strip()
    assert err == f"ledger: error: ValueError: {inputs[3]}: expected a JSON dict, found list"
    assert not (tmp_path / "out").exists()
