"""The split stage's entry point: reads its params section, stops with one clear line on bad input."""

from __future__ import annotations

import json

import pytest
import typer

from pipeline.stages import split
from tests.dataset.resampled import make_input


def test_cli_entry_reads_params(tmp_path):
    # Given params.yaml training the data's two angles and marking the 45 deg held-out batch and the
    # second cast as external
    src = make_input(tmp_path / "in")
    params = tmp_path / "params.yaml"
    params.write_text(
        "train:\n  angles: [30, 45]\n"
        "split:\n  seed: 3\n  external_batches: ['*heldout-45*', 'sim-tissue-2']\n"
    )
    # When the stage's entry point runs
    split.main(src, tmp_path / "out", params)
    manifest = json.loads((tmp_path / "out" / "manifest.json").read_text())
    # Then the globs decide what is external
    ext30 = {d["batch_id"] for d in manifest["angles"]["30"]["splits"]["external"]}
    ext45 = {d["batch_id"] for d in manifest["angles"]["45"]["splits"]["external"]}
    assert ext30 == {"sim-tissue-2"} and ext45 == {"sim-tissue-2", "sim-heldout-45deg"}


def test_a_batch_without_its_metadata_exits_1_with_the_reason(tmp_path, capsys):
    # Given a resampled batch whose .json is missing
    src = make_input(tmp_path / "in")
    (src / "sim-tissue-1.json").unlink()
    params = tmp_path / "params.yaml"
    params.write_text("split:\n  seed: 0\n")
    # When the stage runs / Then it stops with exit code 1 and one line naming the file
    with pytest.raises(typer.Exit) as exit_info:
        split.main(src, tmp_path / "out", params)
    assert exit_info.value.exit_code == 1
    err = capsys.readouterr().err
    assert err.startswith("split: error: ") and "sim-tissue-1.parquet: no sim-tissue-1.json" in err
