"""evaluation.json is one typed document: a section missing or renamed fails where the file is
written or read, naming the file and the field, not as an empty table in the report."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from pipeline.metrics.document import read_evaluation, write_evaluation
from tests.metrics.documents import evaluation
from tests.metrics.fakes import gap_error, in_memory_metrics


def _whole() -> dict:
    """A whole evaluation as the evaluate stage builds it (force sections from fake predictors)."""
    return in_memory_metrics(gap_error).model_dump(exclude_none=True)


def test_what_is_written_is_read_back_field_for_field(tmp_path: Path) -> None:
    # given: a whole evaluation; when: written and read back
    doc = _whole()
    written = write_evaluation(tmp_path / "evaluation.json", doc)
    read = read_evaluation(tmp_path / "evaluation.json")
    # then: the same document, its fields typed (rounded on disk: equal at the written precision)
    assert read.gaps_deg == written.gaps_deg == ["15", "30"]
    assert read.within_angle["fnn"]["30"]["fx"].nrmse_pct == pytest.approx(
        written.within_angle["fnn"]["30"]["fx"].nrmse_pct, abs=1e-4
    )
    assert read.mean["ls"].n_angles == 6


def test_a_section_renamed_in_the_file_fails_on_reading_naming_file_and_field(tmp_path: Path) -> None:
    # given: an evaluation.json whose "unit_transfer" a change renamed to "transfer"
    doc = _whole()
    doc["transfer"] = doc.pop("unit_transfer")
    path = tmp_path / "evaluation.json"
    path.write_text(json.dumps(doc))
    # when / then: reading it fails, naming the file, the missing field and the unknown one
    with pytest.raises(ValueError) as found:
        read_evaluation(path)
    assert str(path) in str(found.value)
    assert "unit_transfer" in str(found.value) and "transfer" in str(found.value)


def test_a_document_lacking_a_section_is_not_written(tmp_path: Path) -> None:
    # given: the force sections alone, without the per-unit and cue sections
    doc = _whole()
    del doc["cues"]
    # when / then: nothing is written, and the error names the section
    with pytest.raises(ValueError, match="cues"):
        write_evaluation(tmp_path / "evaluation.json", doc)
    assert not (tmp_path / "evaluation.json").exists()


def test_a_missing_figure_of_a_row_is_an_error_not_an_empty_cell() -> None:
    # given: a unit-transfer row without its ratio; when / then: the document refuses it
    row = {"same_unit": 4.0, "new_uncalibrated": 5.0, "new_calibrated": 4.4}
    with pytest.raises(ValueError, match="ratio"):
        evaluation(unit_transfer={"champion": row})
