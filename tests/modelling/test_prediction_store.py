"""The predict stage's record of what each model reads: one writer, one reader, typed."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from needlecue_runtime.features import ModelInputs
from pipeline.modelling.choice import Choice
from pipeline.modelling.prediction_store import INPUTS_FILE, ModelReads, read_inputs, write_inputs

CHOSEN = Choice("rest_volts", {"volts": 9.1, "rest_volts": 5.2}, "leave-one-unit-out (3 units)", "ridge")


def test_what_each_model_reads_is_read_back_as_written(tmp_path: Path) -> None:
    # given: a pinned model and one whose inputs were chosen by validation
    reads = {"ls": {"30": ModelReads(ModelInputs(kind="volts"), None)}}
    reads["fnn"] = {"30": ModelReads(ModelInputs(kind="rest_volts"), CHOSEN)}
    # when: written by the predict stage and read by the report
    write_inputs(reads, tmp_path)
    # then: the same records
    assert read_inputs(tmp_path) == reads


def test_a_record_without_its_choice_fails_naming_the_file(tmp_path: Path) -> None:
    # given: a record that lost its `inputs_choice` field
    (tmp_path / INPUTS_FILE).write_text(json.dumps({"ls": {"30": {"inputs": {"kind": "volts"}}}}))
    # when / then
    with pytest.raises(ValueError, match=r"inputs\.json.*inputs_choice"):
        read_inputs(tmp_path)
