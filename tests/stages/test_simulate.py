"""The simulate stage's entry point: reads its params section, stops with one clear line on bad input."""

from __future__ import annotations

from pathlib import Path

import pytest
import typer
import yaml

from pipeline.stages import simulate

SMALL = {
    "angles_deg": [15],
    "train_batches": 1,
    "trials_per_angle": 1,
    "heldout_trials_per_angle": 1,
    "calibration_trials_per_angle": 1,
    "units": ["est-sim-001"],
    "new_units": ["est-sim-101"],
}


def _params(tmp_path: Path, section: dict) -> Path:
    p = tmp_path / "params.yaml"
    p.write_text(yaml.safe_dump({"simulate": section}))
    return p


def test_writes_the_batches_of_its_params_section(tmp_path, capsys):
    # When the stage runs on a small plan
    simulate.main(tmp_path / "sim", _params(tmp_path, SMALL))
    # Then it writes that plan's batches and says so batch by batch
    assert sorted(p.name for p in (tmp_path / "sim").iterdir()) == [
        "sim-calib-est-sim-101",
        "sim-heldout-15deg",
        "sim-heldout-15deg-est-sim-101",
        "sim-tissue-1-est-sim-001",
        "simulate.json",
    ]
    assert "simulate: sim-tissue-1-est-sim-001: 1 trials" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("section", "folder_file", "reason"),
    [
        (SMALL, "precious.csv", "not written by the simulator"),
        ({**SMALL, "trails_per_angle": 3}, None, "trails_per_angle"),
        ({**SMALL, "unit_id": "est-sim-001"}, None, "unit_id"),
        ({**SMALL, "new_units": ["est-sim-001"]}, None, "disjoint"),
    ],
    ids=["foreign folder", "params typo", "the old unit_id", "a unit both training and new"],
)
def test_bad_input_exits_1_with_the_reason(tmp_path, capsys, section, folder_file, reason):
    # Given a folder holding someone's data, or a typo in the params section
    out = tmp_path / "out"
    if folder_file:
        out.mkdir()
        (out / folder_file).write_text("1,2,3\n")
    # When the stage runs
    with pytest.raises(typer.Exit) as exit_info:
        simulate.main(out, _params(tmp_path, section))
    # Then it stops with exit code 1 and one line saying why, leaving the folder as it was
    assert exit_info.value.exit_code == 1
    err = capsys.readouterr().err
    assert err.startswith("simulate: error: ") and reason in err
    if folder_file:
        assert [p.name for p in out.iterdir()] == [folder_file]
    else:
        assert not out.exists()
