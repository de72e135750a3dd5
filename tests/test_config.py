"""params.yaml sections: a typo or a bad value fails loudly."""

from __future__ import annotations

from pathlib import Path

import pytest
from pydantic import ValidationError

from pipeline.config import CuesParams, load_section


def test_bad_params_fail_loudly(tmp_path: Path) -> None:
    # given: a typo, a wrong value, and an inconsistent pair
    with pytest.raises(ValidationError, match="debounce"):
        CuesParams.model_validate({"debounce": 0.3})
    with pytest.raises(ValidationError):
        CuesParams.model_validate({"kinds": ["gru"]})
    with pytest.raises(ValidationError, match="increasing"):
        CuesParams(evidence_levels=(0.2, 0.1))
    with pytest.raises(ValidationError, match="stop_from_deg"):
        CuesParams(continue_below_deg=20, stop_from_deg=10)
    # and through params.yaml: an unknown key in the section fails, a missing section is the defaults
    path = tmp_path / "params.yaml"
    path.write_text("cues:\n  min_confidense: 0.8\n")
    with pytest.raises(ValidationError, match="min_confidense"):
        load_section(CuesParams, "cues", path)
    path.write_text("train:\n  angles: [0]\n")
    assert load_section(CuesParams, "cues", path) == CuesParams()
