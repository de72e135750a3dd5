"""expectations: GX 1.x suites on small frames, failures mapped back to trial, file, line and column."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from pipeline.config import IngestParams
from pipeline.rig import datadocs, expectations


@pytest.fixture(scope="module")
def validator() -> expectations.Validator:
    return expectations.Validator(IngestParams(min_samples=3, min_rate_hz=5.0, max_rate_hz=1000.0))


def fsr_frame(rows: list[tuple[str, int, float, float]]) -> pd.DataFrame:
    """(trial_id, line, t_ms, ch) rows as the concatenated fsr frame ingest builds."""
    frame = pd.DataFrame(rows, columns=["trial_id", "line", "t_ms", "ch"]).astype({"trial_id": object})
    frame["dt"] = expectations.frame_dt(frame, "t_ms")
    return frame


def summary(problems) -> set[tuple]:
    return {(p.trial_id, p.file, p.line, p.column, p.reason) for p in problems}


def test_stream_failures_map_to_trial_line_and_column(validator):
    # Given two trials of 10-bit counts: trial a has an out-of-range count, a missing value
    # and a repeated timestamp; trial b starts its clock again (that is not a time step)
    frame = fsr_frame(
        [
            ("a", 2, 0.0, 10),
            ("a", 3, 20.0, 1100),
            ("a", 4, 20.0, 12),
            ("a", 5, 60.0, np.nan),
            ("b", 2, 0.0, 10),
            ("b", 3, 20.5, 1023),
            ("b", 4, 40.0, 0),
        ]
    )
    # When the fsr suite validates the frame
    check = validator.stream("bx", "fsr", frame, "t_ms", ["ch"], 1023, "bx", lambda t: f"{t}.fsr.csv")
    # Then each failure is a Problem at its trial/file/line/column, and trial b has none
    assert summary(check.problems) == {
        ("a", "a.fsr.csv", 3, "ch", "count 1100 outside the ADC range [0, 1023]"),
        ("a", "a.fsr.csv", 4, "t_ms", "time does not increase: step of 0 ms from the previous sample"),
        ("a", "a.fsr.csv", 5, "ch", "missing value (empty cell or NaN)"),
    }
    assert not check.batch_failed and check.result["success"] is False


def test_trial_table_checks(validator):
    # Given a trials table with a bad id, a repeated id, a missing angle and an empty tissue point
    frame = pd.DataFrame(
        {
            "trial_id": ["ok", "bad id", "dup", "dup", "t5"],
            "angle_deg": [0.0, 15.0, 30.0, 30.0, np.nan],
            "tissue_point": ["P1", "P1", "P2", "", "P3"],
            "line": [2, 3, 4, 5, 6],
        }
    ).astype({"trial_id": object, "tissue_point": object})
    # When it is validated
    check = validator.trials("bx", frame, "trials.csv")
    # Then every bad row is named by line and column; both copies of a repeated id are
    got = {(p.line, p.column) for p in check.problems}
    assert got == {(3, "trial_id"), (4, "trial_id"), (5, "trial_id"), (5, "tissue_point"), (6, "angle_deg")}


def test_stream_summary_checks_samples_and_rate(validator):
    # Given per-file summaries: too few samples, too slow, fine
    frame = pd.DataFrame(
        {
            "trial_id": ["a", "b", "c"],
            "file": ["a.fsr.csv", "b.ref.csv", "c.fsr.csv"],
            "time_column": ["t_ms", "t_s", "t_ms"],
            "n_samples": [2, 100, 100],
            "rate_hz": [50.0, 0.5, 30.0],
        }
    )
    # When it is validated
    check = validator.streams("bx", frame, "bx", lambda name: name)
    # Then the first two are named with their file, the rate blames the time column
    assert {(p.trial_id, p.file, p.column) for p in check.problems} == {
        ("a", "a.fsr.csv", None),
        ("b", "b.ref.csv", "t_s"),
    }


def test_a_failure_without_rows_fails_the_batch(validator):
    # Given a frame that lacks a column the suite expects
    frame = fsr_frame([("a", 2, 0.0, 1.0), ("a", 3, 20.0, 1.0), ("a", 4, 40.0, 1.0)]).drop(columns="ch")
    # When it is validated / Then the Problem names the column and the batch is suspect
    check = validator.stream("bx", "fsr", frame, "t_ms", ["ch"], None, "bx", lambda t: t)
    assert check.batch_failed
    assert any(p.column == "ch" and p.line is None for p in check.problems)


def test_stored_results_are_deterministic_and_render_as_data_docs(tmp_path):
    # Given the same frame validated in two separate GX contexts
    frame = fsr_frame([("a", 2, 0.0, 1.0), ("a", 3, 20.0, 2000.0), ("a", 4, 40.0, 1.0)])
    results = [
        expectations.Validator(IngestParams())
        .stream("bx", "fsr", frame, "t_ms", ["ch"], 1023, "bx", lambda t: t)
        .result
        for _ in range(2)
    ]
    # Then the stored JSON is identical (no run times, no random ids)
    assert json.dumps(results[0]) == json.dumps(results[1])
    assert "run_id" not in results[0]["meta"] and "id" not in results[0]
    # When the stored JSON (as reused batches have it) is rendered as Data Docs
    stored = json.loads(json.dumps(results[0]))
    index = datadocs.write_data_docs({"bx": {"fsr": stored}}, tmp_path / "docs")
    # Then there is an index page and a validation page a person can open
    assert index == tmp_path / "docs" / "index.html" and index.is_file()
    pages = list(Path(tmp_path / "docs" / "validations").rglob("*.html"))
    assert len(pages) == 1 and "bx.fsr" in index.read_text()
    # And rendering it again gives the same bytes (no render times or random element ids)
    again = datadocs.write_data_docs({"bx": {"fsr": stored}}, tmp_path / "docs2")
    first = sorted(p.relative_to(tmp_path / "docs") for p in (tmp_path / "docs").rglob("*.html"))
    assert first == sorted(p.relative_to(again.parent) for p in again.parent.rglob("*.html"))
    for rel in first:
        assert (tmp_path / "docs" / rel).read_bytes() == (again.parent / rel).read_bytes(), rel
