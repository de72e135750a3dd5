"""A checkpoint's metadata as a typed document: what `save_checkpoint` writes `load_checkpoint` reads
back, the dict unchanged; a renamed or missing field, another format or a missing group of tensors
fails, naming the file and the field."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
import torch

from pipeline.modelling.checkpoint import (
    ModelConfig,
    checkpoint_meta,
    checkpoint_sha256,
    load_checkpoint,
    save_checkpoint,
)
from pipeline.modelling.fit import fit
from pipeline.modelling.kinds.ls import LSParams
from tests.modelling.frames import CHANNELS, make_frame


@pytest.fixture(scope="module")
def checkpoint() -> dict[str, Any]:
    """An LS model's checkpoint, as the train stage makes it."""
    return fit("ls", LSParams(), make_frame(2, seed=0), train_data_sha256="abc").checkpoint


def test_a_saved_checkpoint_loads_back_unchanged_and_describes_itself(
    checkpoint: dict[str, Any], tmp_path: Path
) -> None:
    # given / when: saved, then loaded
    save_checkpoint(checkpoint, tmp_path / "model.pt")
    found = load_checkpoint(tmp_path)
    meta = checkpoint_meta(found)
    # then: the same dict (the same model, by its hash), its metadata typed
    assert set(found) == set(checkpoint)
    assert checkpoint_sha256(found) == checkpoint_sha256(checkpoint)
    assert (meta.kind, meta.channels, meta.targets, meta.train_data_sha256) == (
        "ls",
        CHANNELS,
        ["fx", "fy", "fz"],
        "abc",
    )
    assert isinstance(meta.config, ModelConfig) and meta.config.n_in == len(CHANNELS)


@pytest.mark.parametrize("field", ["channels", "torch_version"])
def test_a_missing_field_fails_loading_naming_the_file_and_the_field(
    checkpoint: dict[str, Any], tmp_path: Path, field: str
) -> None:
    # given: a checkpoint file without one of its fields (written around the checked writer)
    torch.save({k: v for k, v in checkpoint.items() if k != field}, tmp_path / "model.pt")
    # when / then
    with pytest.raises(ValueError, match=rf"(?s)model\.pt: not a checkpoint this needlecue reads.*{field}"):
        load_checkpoint(tmp_path)


def test_a_renamed_field_fails_saving_naming_both_and_writes_nothing(
    checkpoint: dict[str, Any], tmp_path: Path
) -> None:
    # given: `targets` renamed
    renamed = {("axes" if k == "targets" else k): v for k, v in checkpoint.items()}
    # when / then
    with pytest.raises(ValueError, match=r"(?s)model\.pt \(being written\).*targets.*axes"):
        save_checkpoint(renamed, tmp_path / "model.pt")
    assert not (tmp_path / "model.pt").exists()


def test_another_format_or_missing_tensors_are_said(checkpoint: dict[str, Any]) -> None:
    # given / when / then: an older format named, and a checkpoint without its weights
    with pytest.raises(
        ValueError, match=r"here: not a needlecue-model/1 checkpoint \(format 'needlecue-model/0'\)"
    ):
        checkpoint_meta({**checkpoint, "format": "needlecue-model/0"}, "here")
    with pytest.raises(ValueError, match="here: a needlecue-model/1 checkpoint without its state_dict"):
        checkpoint_meta({k: v for k, v in checkpoint.items() if k != "state_dict"}, "here")
