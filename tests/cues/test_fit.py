"""Fitting cue packs: small strict JSON, the angle estimator's LDA form, what cannot be built."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pipeline.cues import fit as cue_fit
from tests.cues.synthetic import (
    ANGLES,
    CHANNELS,
    RATE,
)


def test_pack_is_small_json_and_round_trips(pack30: dict) -> None:
    # given: a pack built from the training splits
    # when: it goes through JSON
    text = json.dumps(pack30)
    back = json.loads(text)
    # then: nothing is lost, it is small, and it says what it is
    assert back == pack30
    assert len(text) < 100_000
    assert pack30["format"] == "needlecue-cues/1"
    assert pack30["channels"] == list(CHANNELS)
    assert pack30["angles"] == [float(a) for a in ANGLES]
    assert pack30["rate_hz"] == pytest.approx(RATE, rel=1e-3)
    prof = pack30["standard_profile"]
    assert len(prof["mean_n"]) == len(prof["sd_n"]) and len(prof["mean_n"][0]) == 3
    assert set(pack30["thresholds"]["profile"]) == {"reference"}  # no predictor given


def test_binary_lda_in_the_multiclass_form_gives_sklearns_posterior() -> None:
    # given: a two-class LDA (scikit-learn keeps one row of coefficients for it)
    rng = np.random.default_rng(0)
    x = np.vstack([rng.normal(0, 1, (8, 3)), rng.normal(1, 1, (8, 3))])
    y = np.repeat([0, 1], 8)
    model = cue_fit._fit_lda("auto", 2, x, y)
    # when: put in the two-row form, and scored the same way
    coef, intercept = cue_fit._multiclass_form(model)
    scores = cue_fit._scores(model, x)
    # then: two rows, and the softmax of the scores is scikit-learn's posterior
    assert coef.shape == (2, 3) and intercept.shape == (2,)
    np.testing.assert_allclose(x @ coef.T + intercept, scores, atol=1e-9)
    np.testing.assert_allclose(cue_fit._softmax(scores), model.predict_proba(x), atol=1e-9)


def test_two_angles_give_a_two_class_estimator(two_angle_pack: dict) -> None:
    # given / when: a pack from two angles' training trials
    est = two_angle_pack["angle_estimator"]
    # then: every stage scores both classes, and the pack is strict JSON
    assert est["classes_deg"] == [30.0, 45.0]
    for stage in est["stages"]:
        assert np.asarray(stage["coef"]).shape == (2, 3 * (est["stages"].index(stage) + 1))
        assert len(stage["intercept"]) == 2
    assert "unavailable" not in two_angle_pack
    json.dumps(two_angle_pack, allow_nan=False)
