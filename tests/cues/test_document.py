"""The cue evaluation is one typed document: written by the cues stage, read by evaluate and report;
a field renamed or missing fails where the file is written or read, naming it."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from pipeline.config import CuesParams
from pipeline.cues.document import ScoredCues, SkippedCues, read_cue_evaluation, write_cue_evaluation
from pipeline.cues.packs import build_cue_pack
from pipeline.cues.score import evaluate_cues, skipped_evaluation
from tests.cues.synthetic import external_split, zero_forces


@pytest.fixture
def scored(train_by_angle: dict, params: CuesParams) -> dict:
    """A cue evaluation of a 30° pack on one external trial per angle, as the stage computes it."""
    external = external_split(1)
    pack = build_cue_pack(train_by_angle, 30, params)
    return evaluate_cues(external, params, {30: pack}, zero_forces(external), log=lambda _m: None)


def test_a_scored_evaluation_is_written_and_read_back_as_one(scored: dict, tmp_path: Path) -> None:
    # when: written as the stage writes it, and read as the report reads it
    written = write_cue_evaluation(tmp_path / "evaluation.json", scored)
    read = read_cue_evaluation(tmp_path / "evaluation.json")
    # then: a scored evaluation, its fields typed
    assert isinstance(read, ScoredCues) and read.kinds == written.kinds == ["ls"]
    coverage = scored["results"]["ls"]["combined"]["seen"]["coverage_frames"]
    assert read.results["ls"]["combined"].seen.coverage_frames == pytest.approx(coverage, abs=1e-6)


def test_a_skipped_evaluation_says_why(params: CuesParams, tmp_path: Path) -> None:
    # given: nothing to score; when: written and read
    write_cue_evaluation(tmp_path / "evaluation.json", skipped_evaluation("no cue pack", {}, params))
    read = read_cue_evaluation(tmp_path / "evaluation.json")
    # then: a skipped evaluation, with the reason
    assert isinstance(read, SkippedCues) and read.skipped == "no cue pack" and read.results == {}


def test_a_field_renamed_in_the_file_fails_naming_the_file_and_the_field(
    scored: dict, tmp_path: Path
) -> None:
    # given: a cue evaluation whose method results call `seen` `shown`
    combined = scored["results"]["ls"]["combined"]
    combined["shown"] = combined.pop("seen")
    path = tmp_path / "evaluation.json"
    path.write_text(json.dumps(scored))
    # when / then: reading it fails, naming the file and the fields
    with pytest.raises(ValueError) as found:
        read_cue_evaluation(path)
    assert str(path) in str(found.value) and "seen" in str(found.value) and "shown" in str(found.value)


def test_an_evaluation_lacking_a_field_is_not_written(scored: dict, tmp_path: Path) -> None:
    del scored["truth"]
    with pytest.raises(ValueError, match="truth"):
        write_cue_evaluation(tmp_path / "evaluation.json", scored)
    assert not (tmp_path / "evaluation.json").exists()
