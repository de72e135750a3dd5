"""A unit's calibration document as typed models: what the writer writes the reader reads back, in
the bytes needlecue-unit/4 files have always had; a renamed or missing field, an older format or a
malformed transform fails, naming the file and what is wrong."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from needlecue_runtime.unit_calibration import (
    calibrated_units,
    parse_unit,
    read_unit,
    read_units,
    transform_for,
    write_unit,
)

SHA = "ab" * 32


def unit_doc(unit_id: str = "est-7") -> dict[str, Any]:
    """A calibration document as `calibrate_unit` builds it: an LS transform through the 30° model,
    one trial set aside (its reason with a degree sign), the cue evidence read through a map."""
    evidence = {"30": {"n": [2, 1], "means": [[0.1, 0.2, 0.3], [0.4, 0.5, 0.6]]}}
    return {
        "format": "needlecue-unit/4",
        "unit_id": unit_id,
        "batches": ["cal-1"],
        "trials": [{"batch_id": "cal-1", "trial_id": "t01", "angle": "30"}],
        "angles_used": ["30"],
        "angles_missing": ["45"],
        "set_aside": [
            {
                "batch_id": "cal-1",
                "trial_id": "t02",
                "file": "cal-1/t02.fsr.csv",
                "angle": "60",
                "reason": "no shared model is trained at 60° (train.angles)",
            }
        ],
        "transforms": {
            "ls": {
                "matrix": np.eye(3).tolist(),
                "offset": [0.0, 0.5, -0.25],
                "domain": "inputs",
                "fitted_through": ["30"],
                "models": {"30": SHA},
                "loss_before": 1.5,
                "loss_after": 0.25,
            }
        },
        "params": {"ridge": 0.01, "transform": "full"},
        "front_end": None,
        "cues": {
            "levels": [0.05, 0.1],
            "evidence": evidence,
            "mapped": {"kind": "ls", "matrix": np.eye(3).tolist(), "offset": [0, 0, 0], "evidence": evidence},
        },
    }


def test_a_written_document_reads_back_as_written_in_the_bytes_of_needlecue_unit_4(tmp_path: Path) -> None:
    # given: a calibration document
    doc = unit_doc()
    # when: written, then read
    path = write_unit(doc, tmp_path)
    unit = read_unit(path)
    # then: the file is <unit_id>.json in the format's bytes (sorted keys, 2-space indent, ASCII)
    assert path == tmp_path / "est-7.json"
    assert path.read_text() == json.dumps(doc, indent=2, sort_keys=True) + "\n"
    assert "\\u00b0" in path.read_text()
    # and the reader gives back every field, the cue section as stored
    assert unit.unit_id == "est-7" and unit.set_aside[0].angle == "60"
    assert unit.transforms["ls"].models == {"30": SHA} and unit.transforms["ls"].identity_kept is None
    assert unit.cue_section() == json.loads(path.read_text())["cues"]
    assert calibrated_units(read_units(tmp_path)) == {"est-7": True}


def test_the_transform_applies_only_to_the_models_it_was_made_with(tmp_path: Path) -> None:
    # given: the document read back
    unit = read_unit(write_unit(unit_doc(), tmp_path))
    # when / then: the 30° LS model it was made with gets its transform; another model, kind or angle none
    found = transform_for(unit, "ls", 30.0, SHA)
    assert found is not None and found.offset == (0.0, 0.5, -0.25)
    assert transform_for(unit, "ls", "30", "cd" * 32) is None
    assert transform_for(unit, "fnn", "30", SHA) is None
    assert transform_for(unit, "ls", "45", SHA) is None


@pytest.mark.parametrize("field", ["angles_used", "front_end"])
def test_a_missing_field_fails_reading_naming_the_file_and_the_field(tmp_path: Path, field: str) -> None:
    # given: a document without one of its fields
    doc = unit_doc()
    del doc[field]
    path = tmp_path / "est-7.json"
    path.write_text(json.dumps(doc))
    # when / then
    with pytest.raises(ValueError, match=rf"(?s)est-7\.json: not a calibration document.*{field}"):
        read_unit(path)


def test_a_renamed_field_fails_writing_naming_it_and_writes_nothing(tmp_path: Path) -> None:
    # given: a transform whose `models` was renamed
    doc = unit_doc()
    doc["transforms"]["ls"]["checkpoints"] = doc["transforms"]["ls"].pop("models")
    # when / then: both names said, no file left
    with pytest.raises(ValueError, match=r"(?s)being written.*transforms\.ls\.models.*checkpoints"):
        write_unit(doc, tmp_path)
    assert list(tmp_path.iterdir()) == []


def test_an_older_format_says_to_calibrate_the_unit_again(tmp_path: Path) -> None:
    # given: a needlecue-unit/3 document, and something that is no calibration at all
    old, other = tmp_path / "old.json", tmp_path / "other.json"
    old.write_text(json.dumps({**unit_doc(), "format": "needlecue-unit/3"}))
    other.write_text('{"format": "other"}')
    # when / then
    with pytest.raises(
        ValueError, match=r"old\.json: not a needlecue-unit/4 document .*calibrate the unit again"
    ):
        read_unit(old)
    with pytest.raises(ValueError, match=r"other\.json: not a needlecue-unit/4 document \(format 'other'\)$"):
        read_unit(other)


def test_a_malformed_transform_is_named_by_its_kind() -> None:
    # given: an LS transform whose matrix is not square
    doc = unit_doc()
    doc["transforms"]["ls"]["matrix"] = [[1.0, 0.0]]
    # when / then
    with pytest.raises(ValueError, match=r"here: transform 'ls': an input transform is a finite square"):
        parse_unit(doc, "here")
