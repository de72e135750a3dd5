"""The report's angle-cue section from the cue evaluation and the typed packs."""

from __future__ import annotations

from pathlib import Path

import pytest

from needlecue_runtime.cues.pack import as_pack, read_pack, write_pack
from pipeline.config import CuesParams
from pipeline.cues.document import CUE_EVALUATION_DOC
from pipeline.cues.packs import build_cue_pack
from pipeline.cues.score import skipped_evaluation
from pipeline.reporting import cue_figures
from pipeline.reporting.cues import angle_cues
from tests.cues.synthetic import ANGLES, make_split

PARAMS = CuesParams(kinds=("ls",), evidence_levels=(0.05, 0.1, 0.2))


@pytest.fixture(scope="module")
def packs() -> dict:
    train = {float(a): make_split(a, ["b1", "b2"], 3, seed=1) for a in ANGLES}
    return {30.0: build_cue_pack(train, 30, PARAMS)}


def test_a_skipped_evaluation_says_what_was_built_and_why_nothing_was_scored(
    packs: dict, tmp_path: Path
) -> None:
    # given: an evaluation that scored nothing, and the packs as the cues stage wrote them
    evaluation = CUE_EVALUATION_DOC.adapter.validate_python(
        skipped_evaluation("no external trials", packs, PARAMS)
    )
    write_pack(tmp_path / "30.json", packs[30.0])
    read = {30.0: read_pack(tmp_path / "30.json")}
    # when
    text = angle_cues(evaluation, read)
    # then: what the packs hold, in words, and why nothing was scored
    assert text.startswith("## Angle cues")
    assert "the standard force profile of 30°" in text and "paper-method thresholds (reference)" in text
    assert f"an angle estimator over {', '.join(f'{float(a):g}°' for a in ANGLES)}" in text
    assert "**Cue evaluation skipped**: no external trials" in text
    # and: a pack as built (a dict) reads the same as the typed one
    assert angle_cues(evaluation, packs) == text == angle_cues(evaluation, {30.0: as_pack(packs[30.0])})


def test_a_skipped_evaluation_draws_figures_that_say_why(packs: dict, tmp_path: Path) -> None:
    # given: an evaluation that scored nothing
    evaluation = CUE_EVALUATION_DOC.adapter.validate_python(
        skipped_evaluation("no external trials", packs, PARAMS)
    )
    # when
    cue_figures.plot_confusion(evaluation, tmp_path / "c.png")
    cue_figures.plot_time_to_cue(evaluation, tmp_path / "t.png")
    # then: both figures exist, placeholders of the same message
    assert (tmp_path / "c.png").read_bytes() == (tmp_path / "t.png").read_bytes()
