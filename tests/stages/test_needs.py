"""The needs stage on a small processed folder: deterministic needs.json and needs.png on one worker or
two, the report's section rendered from them, missing inputs named, odd data said instead of failing."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import typer
from typer.testing import CliRunner

from pipeline.needs.document import read_needs
from pipeline.reporting.needs import how_much_data_you_need
from pipeline.stages import needs
from tests.helpers import tree_hash
from tests.needs.lab import lab_frames, write_choices, write_lab

PARAMS = (
    "cues:\n  kinds: [ls]\n  evidence_levels: [0.05, 0.1, 0.2]\nneeds:\n  calibration_insertions: [1, 2]\n"
)


def invoke(*args: str):
    app = typer.Typer()
    app.command()(needs.main)
    return CliRunner().invoke(app, list(args))


def test_stage_writes_the_same_bytes_on_one_worker_or_two(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # given: two training units on three angles (8 insertions per angle), a new unit with a calibration
    # batch, the choose stage's files
    processed = write_lab(tmp_path / "processed", lab_frames(units=("A", "B"), angles=(15, 30, 45)))
    choices = write_choices(tmp_path / "choices")
    params = tmp_path / "params.yaml"
    params.write_text(PARAMS)
    # when: running the stage in-process and on two worker processes
    outs = {n: tmp_path / f"out{n}" for n in ("1", "2")}
    for n, out in outs.items():
        monkeypatch.setenv("NEEDLECUE_WORKERS", n)
        result = invoke(str(processed), str(choices), str(out), "--params", str(params))
        assert result.exit_code == 0, result.output
    # then: needs.json and needs.png, byte-identical both times
    h1 = tree_hash(outs["1"])
    assert set(h1) == {"needs.json", "needs.png"}
    assert h1 == tree_hash(outs["2"])
    doc = json.loads((outs["1"] / "needs.json").read_text())
    assert doc["format"] == "needlecue-needs/1"
    assert doc["training"]["ladder"] == [3, 6, 8]
    assert [s["k"] for s in doc["calibration"]["new_units"]["D"]["steps"]] == [1, 2]
    assert sorted(doc["calibration"]["leave_one_unit_out"]["units"]) == ["A", "B"]
    # and the advice is in needs.json and in the log
    assert doc["advice"] and all(f"advice: {line}" in result.output for line in doc["advice"])
    # and the report's section renders from it, linking the figure relative to reports/
    section = how_much_data_you_need(read_needs(outs["1"] / "needs.json"))
    assert section.startswith("## How much data you need")
    assert "(needs/needs.png)" in section and doc["advice"][0] in section


def test_stage_names_missing_inputs(tmp_path: Path) -> None:
    # given: no processed data / when: running the stage / then: exit 1 naming the folder
    params = tmp_path / "params.yaml"
    params.write_text("{}\n")
    result = invoke(
        str(tmp_path / "nowhere"), str(tmp_path / "choices"), str(tmp_path / "out"), "--params", str(params)
    )
    assert result.exit_code == 1
    assert "nowhere" in result.output


def test_odd_data_is_said_and_never_stops_the_stage(tmp_path: Path) -> None:
    # given: one angle, one unit, no held-out trials, no calibration batch, no choose stage's files
    frames = lab_frames(units=("A",), angles=(30,))
    frames["external"] = {a: f.iloc[:0] for a, f in frames["external"].items()}
    frames["calibration"] = {}
    processed = write_lab(tmp_path / "processed", frames)
    params = tmp_path / "params.yaml"
    params.write_text(PARAMS)
    # when
    out = tmp_path / "out"
    result = invoke(str(processed), str(tmp_path / "no-choices"), str(out), "--params", str(params))
    # then: exit 0, both outputs, and every figure that could not be computed is said, with why
    assert result.exit_code == 0, result.output
    doc = json.loads((out / "needs.json").read_text())
    said = {n["what"]: n["why"] for n in doc["not_computed"]}
    assert said["force of ls"].endswith("ls.json: missing (run the choose stage)")
    assert said["cues against training insertions"] == "no external trial of a training unit"
    assert said["cues"] == "one trained angle (30°): nothing to tell apart"
    assert said["leave-one-unit-out calibration curve"].startswith("one training unit (A)")
    assert (out / "needs.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "Not computed, and why:" in how_much_data_you_need(read_needs(out / "needs.json"))
