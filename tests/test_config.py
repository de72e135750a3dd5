"""params.yaml sections: a typo or a bad value fails loudly."""

from __future__ import annotations

from pathlib import Path

import pytest
from pydantic import ValidationError

from pipeline.config import CuesParams, RegisterParams, TrainParams, load_section


def test_bad_params_fail_loudly(tmp_path: Path) -> None:
    # given: a typo, a wrong value, and an inconsistent pair
    with pytest.raises(ValidationError, match="debounce"):
        CuesParams.model_validate({"debounce": 0.3})
    for section, key in ((CuesParams, "kinds"), (TrainParams, "kinds"), (RegisterParams, "candidates")):
        with pytest.raises(ValidationError, match="'ls', 'fnn' or 'lstm'"):  # a model kind's name
            section.model_validate({key: ["ls", "lsmt"]})
    with pytest.raises(ValidationError, match="increasing"):
        CuesParams(evidence_levels=(0.2, 0.1))
    with pytest.raises(ValidationError, match="stop_from_deg"):
        CuesParams(continue_below_deg=20, stop_from_deg=10)
    for k in (0.0, float("inf"), float("nan")):  # the reading divides by it and weighs means by it
        with pytest.raises(ValidationError, match="unit_template_weight"):
            CuesParams(unit_template_weight=k)
    # and through params.yaml: an unknown key in the section fails, a missing section is the defaults
    path = tmp_path / "params.yaml"
    path.write_text("cues:\n  min_confidense: 0.8\n")
    with pytest.raises(ValidationError, match="min_confidense"):
        load_section(CuesParams, "cues", path)
    path.write_text("train:\n  angles: [0]\n")
    assert load_section(CuesParams, "cues", path) == CuesParams()


def test_a_params_file_from_before_the_rename_says_what_the_key_is_now(tmp_path: Path) -> None:
    # given: a lab's params.yaml that still names the model kinds to train `train.models`
    path = tmp_path / "params.yaml"
    path.write_text("train:\n  angles: [0, 15]\n  models: [ls, fnn]\n")
    # when / then: it fails, saying the new name; with it, the kinds are read
    with pytest.raises(ValidationError, match=r"train\.models is now train\.kinds"):
        load_section(TrainParams, "train", path)
    path.write_text("train:\n  angles: [0, 15]\n  kinds: [ls, fnn]\n")
    assert load_section(TrainParams, "train", path).kinds == ("ls", "fnn")
