"""The ingest stage's entry point: which roots it reads, the reports and Data Docs it writes."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import typer

from pipeline.stages import ingest
from tests.rig.batches import A, copy_batch, set_cell


def _params(tmp_path: Path, enabled: bool) -> Path:
    p = tmp_path / "params.yaml"
    p.write_text(f"simulate:\n  enabled: {str(enabled).lower()}\ningest:\n  min_samples: 10\n")
    return p


def test_simulate_disabled_reads_only_raw(raw_dir, lab_bench_a, tmp_path):
    # Given a raw and a simulated batch, and simulate.enabled: false
    copy_batch(lab_bench_a, tmp_path / "sim", "sim-b")
    out = tmp_path / "out"
    # When the stage runs
    ingest.main(raw_dir, tmp_path / "sim", out, tmp_path / "reports", _params(tmp_path, False))
    # Then only the raw batch is ingested
    assert sorted(p.name for p in out.iterdir()) == [A]


def test_stage_writes_reports_and_data_docs(raw_dir, lab_bench_a, tmp_path, capsys, monkeypatch):
    # Given a good raw batch and a simulated batch with one bad cell, simulate enabled, and
    # relative paths as dvc.yaml passes them
    sim_b = copy_batch(lab_bench_a, tmp_path / "sim", "sim-b")
    set_cell(sim_b / "t003.ref.csv", 12, "fy", "oops")
    _params(tmp_path, True)
    monkeypatch.chdir(tmp_path)
    reports = Path("reports")
    # When the stage runs
    ingest.main(Path("raw"), Path("sim"), Path("out"), reports, Path("params.yaml"))
    # Then both batches are ingested, and the reports say what was set aside and where
    assert sorted(p.name for p in Path("out").iterdir()) == [A, "sim-b"]
    quarantine = json.loads((reports / "quarantine.json").read_text())
    assert quarantine == [
        {
            "batch_id": "sim-b",
            "trial_id": "t003",
            "file": "sim/sim-b/t003.ref.csv",
            "line": 12,
            "column": "fy",
            "reason": "text 'oops' in a number column",
        }
    ]
    # and batches.json lists each batch's trials, the one set aside apart (the ledger starts there)
    batches = {b["batch_id"]: b for b in json.loads((reports / "batches.json").read_text())}
    assert batches["sim-b"]["source_dir"] == "sim/sim-b" and batches["sim-b"]["accepted"]
    assert batches["sim-b"]["trials_set_aside"] == ["t003"]
    assert "t003" not in batches["sim-b"]["trials_accepted"] and batches["sim-b"]["trials_accepted"]
    line = "sim/sim-b/t003.ref.csv:12 column 'fy': text 'oops' in a number column"
    assert line in (reports / "summary.md").read_text()
    assert line in capsys.readouterr().err
    assert sorted(p.name for p in (reports / "gx").iterdir()) == [f"{A}.json", "sim-b.json"]
    docs = reports / "data_docs"
    assert (docs / "index.html").is_file()
    assert len(list((docs / "validations").rglob("*.html"))) == 8  # 2 batches x 4 frames
    # When it runs again with nothing changed
    ingest.main(Path("raw"), Path("sim"), Path("out"), reports, Path("params.yaml"))
    # Then both batches are reused and the reports (Data Docs included) are complete again
    assert f"{A}: reused" in capsys.readouterr().err
    assert json.loads((reports / "quarantine.json").read_text()) == quarantine
    assert len(list((docs / "validations").rglob("*.html"))) == 8


def test_output_inside_an_input_folder_exits_1_with_the_reason(raw_dir, tmp_path, capsys):
    # Given an output folder under the raw folder / When the stage runs
    with pytest.raises(typer.Exit) as exit_info:
        ingest.main(
            raw_dir, tmp_path / "sim", raw_dir / "ingested", tmp_path / "reports", _params(tmp_path, True)
        )
    # Then it stops with exit code 1 and one line saying why, and writes nothing there
    assert exit_info.value.exit_code == 1
    assert "ingest: error: output folder" in capsys.readouterr().err
    assert not (raw_dir / "out").exists()
