"""Building cue packs: small strict JSON, what cannot be built."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from pipeline.config import CuesParams
from pipeline.cues.packs import build_cue_pack
from tests.cues.synthetic import (
    ANGLES,
    CHANNELS,
    RATE,
    make_split,
    make_unit_split,
)


def test_pack_is_small_json_and_round_trips(pack30: dict) -> None:
    # given: a pack built from the training splits
    # when: it goes through JSON
    text = json.dumps(pack30)
    back = json.loads(text)
    # then: nothing is lost, it is small, and it says what it is
    assert back == pack30
    assert len(text) < 100_000
    assert pack30["format"] == "needlecue-cues/5"
    assert pack30["channels"] == list(CHANNELS)
    assert pack30["angles"] == [float(a) for a in ANGLES]
    assert pack30["rate_hz"] == pytest.approx(RATE, rel=1e-3)
    prof = pack30["standard_profile"]
    assert len(prof["mean_n"]) == len(prof["sd_n"]) and len(prof["mean_n"][0]) == 3
    assert set(pack30["thresholds"]["profile"]) == {"reference"}  # no predictor given


def test_two_angles_give_a_two_class_estimator(two_angle_pack: dict) -> None:
    # given / when: a pack from two angles' training trials
    est = two_angle_pack["angle_estimator"]
    # then: every stage scores both classes, and the pack is strict JSON
    assert est["classes_deg"] == [30.0, 45.0]
    for j, stage in enumerate(est["stages"]):
        width = 3 * (j + 1)
        assert np.asarray(stage["means"]).shape == (2, width)
        assert np.asarray(stage["precision"]).shape == (width, width)
    assert "unavailable" not in two_angle_pack
    json.dumps(two_angle_pack, allow_nan=False)


@pytest.mark.parametrize(("shrinkage", "estimator"), [(0.0, False), ("auto", True)])
def test_a_channel_that_reads_nothing_needs_shrinkage_or_says_why(shrinkage, estimator: bool) -> None:
    # given: training trials whose third channel reads nothing, and the LDA's shrinkage
    train = {float(a): make_split(a, ["b1", "b2"], 3, seed=int(a) + 1) for a in ANGLES}
    for frame in train.values():
        frame["fsr3"] = 0.0
    params = CuesParams(kinds=("ls",), evidence_levels=(0.05, 0.1, 0.2), lda_shrinkage=shrinkage)
    # when: the pack is built
    pack = build_cue_pack(train, 30, params)
    # then: unshrunk, the singular scatter leaves no angle estimator, and the pack says what to set;
    # shrunk, the estimator is there
    assert (pack["angle_estimator"] is not None) == estimator
    if not estimator:
        assert "cues.lda_shrinkage" in pack["unavailable"]["angle_estimator"]


def test_one_trial_per_unit_and_angle_says_that_nothing_shows_the_scatter() -> None:
    # given: two units with one training trial per angle each
    train = {
        float(a): pd.concat([make_unit_split(a, u, [f"{u}-b1"], 1, seed=k + 1) for k, u in enumerate("AB")])
        for a in ANGLES
    }
    # when: the pack is built
    pack = build_cue_pack(train, 30, CuesParams(kinds=("ls",), evidence_levels=(0.05, 0.1, 0.2)))
    # then: no angle estimator, and the pack says why in words
    assert pack["angle_estimator"] is None
    assert "nothing shows how trials scatter" in pack["unavailable"]["angle_estimator"]
