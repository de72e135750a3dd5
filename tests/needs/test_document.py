"""needs.json as a typed document: what the writer writes the reader reads back, in the bytes the
stage has always written; a renamed or missing field fails, naming the file and the field."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from needlecue_runtime.vocab import dump_json
from pipeline.needs.document import read_needs, write_needs
from tests.needs.docs import needs_doc


def test_a_written_document_reads_back_as_written(tmp_path: Path) -> None:
    # given: a whole needs document
    doc = needs_doc()
    path = tmp_path / "needs.json"
    # when: written, then read
    write_needs(path, doc)
    found = read_needs(path)
    # then: the bytes are the stage's (rounded to 6 decimals, sorted keys, 2-space indent), and the
    # reader gives back every figure
    assert path.read_text() == dump_json(doc, 6)
    assert found.model_dump(mode="json", exclude_none=False) == json.loads(path.read_text())
    assert found.training.steps[1].force["fnn_stand_in"].mean_nrmse_pct == 5.9


@pytest.mark.parametrize("field", ["advice", "cue_within_s"])
def test_a_missing_field_fails_reading_naming_the_file_and_the_field(tmp_path: Path, field: str) -> None:
    # given: a needs.json without one of its fields
    doc = needs_doc()
    del doc[field]
    path = tmp_path / "needs.json"
    path.write_text(json.dumps(doc))
    # when / then
    with pytest.raises(ValueError, match=rf"(?s){path}.*{field}"):
        read_needs(path)


def test_a_renamed_field_fails_writing_naming_the_field_and_writes_nothing(tmp_path: Path) -> None:
    # given: a step whose force figures renamed `mean_nrmse_pct`
    doc = needs_doc()
    doc["training"]["steps"][0]["force"]["ls"]["mean_nrmse"] = doc["training"]["steps"][0]["force"]["ls"].pop(
        "mean_nrmse_pct"
    )
    path = tmp_path / "needs.json"
    # when / then: the writer names the file and both fields, and leaves nothing behind
    with pytest.raises(ValueError, match=r"(?s)needs\.json \(being written\).*mean_nrmse_pct.*mean_nrmse"):
        write_needs(path, doc)
    assert not path.exists()


def test_an_older_format_fails_naming_the_format(tmp_path: Path) -> None:
    # given: a needs.json of another format
    path = tmp_path / "needs.json"
    path.write_text(json.dumps({**needs_doc(), "format": "needlecue-needs/0"}))
    # when / then
    with pytest.raises(ValueError, match=r"(?s)needs\.json.*format"):
        read_needs(path)
