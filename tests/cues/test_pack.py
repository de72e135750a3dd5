"""The cue pack as a typed document: one writer, one reader, the file's bytes as built, a renamed or
missing field named where it fails."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from needlecue_runtime.cues.pack import (
    CuePack,
    as_pack,
    cue_for_deviation,
    pack_format_problem,
    pack_json,
    read_pack,
    sig,
    siglist,
    write_pack,
)
from tests.cues.synthetic import whole_pack


def test_a_written_pack_is_its_compact_sorted_json_and_reads_back_typed(pack30: dict, tmp_path: Path) -> None:
    # given: a pack as built
    path = tmp_path / "packs" / "30.json"
    # when: it is written and read again
    written = write_pack(path, pack30)
    read = read_pack(path)
    # then: the file holds exactly `pack_json`'s text (what the client's model metadata embeds), and
    # the reader gives the same typed document, its fields as attributes
    assert path.read_text() == pack_json(pack30)
    assert read == written
    assert read.preset_angle_deg == 30.0 and read.channels == pack30["channels"]
    assert read.angle_estimator is not None
    assert read.angle_estimator.classes_deg == pack30["angle_estimator"]["classes_deg"]
    assert (
        read.thresholds.profile["reference"].stop_from
        == pack30["thresholds"]["profile"]["reference"]["stop_from"]
    )


def test_a_renamed_field_fails_naming_the_file_and_the_field(pack30: dict, tmp_path: Path) -> None:
    # given: a pack file whose thresholds' `stop_from_deg` was renamed
    doc = json.loads(pack_json(pack30))
    doc["thresholds"]["stop_deg"] = doc["thresholds"].pop("stop_from_deg")
    path = tmp_path / "30.json"
    path.write_text(json.dumps(doc))
    # when / then: reading it fails, naming the file and both fields
    with pytest.raises(ValueError, match=r"30\.json") as e:
        read_pack(path)
    assert "stop_from_deg" in str(e.value) and "stop_deg" in str(e.value)


def test_a_pack_missing_a_field_is_not_written(pack30: dict, tmp_path: Path) -> None:
    # given: a pack without its training summary
    doc = {k: v for k, v in pack30.items() if k != "training"}
    path = tmp_path / "30.json"
    # when / then: the writer refuses it, naming the field, and writes nothing
    with pytest.raises(ValueError, match="training"):
        write_pack(path, doc)
    assert not path.exists()


def test_a_pack_of_another_format_says_so_before_its_fields() -> None:
    # given: a pack of an older format, and something that is no pack at all
    old = {**whole_pack(), "format": "needlecue-cues/4"}
    # then: the format problem says another version made it and how to get a new one
    problem = pack_format_problem(old)
    assert problem is not None and "another needlecue version" in problem
    assert pack_format_problem([1, 2]) is not None
    assert pack_format_problem(whole_pack()) is None
    with pytest.raises(ValueError, match="needlecue-cues/4"):
        as_pack(old)


def test_a_pack_without_estimator_stages_has_no_estimator_and_says_why() -> None:
    # given: a pack whose estimator has no stage, and one whose estimator was not built
    empty = as_pack(whole_pack({"stages": []}))
    none = as_pack({**whole_pack(), "unavailable": {"angle_estimator": "one angle only"}})
    # then: neither has an estimator to read; the reason is the pack's, or the caller's default
    assert empty.estimator is None and none.estimator is None
    assert none.why_missing("angle_estimator", "-") == "one angle only"
    assert empty.why_missing("angle_estimator", "-") == "-"
    assert isinstance(as_pack(empty), CuePack) and as_pack(empty) is empty


@pytest.mark.parametrize(
    ("deviation", "cue"),
    [(0.0, "continue"), (-7.4, "continue"), (7.5, "correct"), (-22.4, "correct"), (22.5, "stop")],
)
def test_a_deviation_maps_to_its_cue_at_the_paper_s_cut_points(deviation: float, cue: str) -> None:
    assert cue_for_deviation(deviation) == cue


def test_numbers_are_kept_to_significant_digits() -> None:
    # then: 6 significant digits by default, nested lists alike, and no negative zero
    assert sig(123.456789) == 123.457 and sig(0.000123456789, 4) == 0.0001235
    assert siglist([[1.23456789, -0.0], [2.0, 3.33333333]]) == [[1.23457, 0.0], [2.0, 3.33333]]
    assert str(sig(-0.0)) == "0.0"
