"""Fitting the angle estimator: its stages, their cross-validation, and what stops it being fitted."""

from __future__ import annotations

import pandas as pd
import pytest

from needlecue_runtime.cues.pack import AngleEstimator
from pipeline.config import CuesParams
from pipeline.cues.estimator import fit_angle_estimator, try_fit_angle_estimator
from tests.cues.synthetic import ANGLES, NOMINAL, make_split


def test_the_estimator_tells_the_trained_angles_apart_stage_by_stage(
    train_by_angle: dict[float, pd.DataFrame], params: CuesParams
) -> None:
    # given: four angles of training trials in two batches, and three loading levels
    logs: list[str] = []
    # when
    est = fit_angle_estimator(train_by_angle, params, logs.append)
    # then: a whole estimator of the pack, its classes the angles in order, one stage at rest and one
    # per level reached, features growing by a direction (3 channels) per stage
    typed = AngleEstimator.model_validate(est)
    assert typed.classes_deg == [float(a) for a in ANGLES]
    assert len(typed.stages) == len(typed.levels) + 1 and typed.levels == list(params.evidence_levels)
    assert [len(s.means[0]) for s in typed.stages] == [3 * (j + 1) for j in range(len(typed.stages))]
    # and: cross-validated by batch, well above chance once the loading direction is seen
    assert typed.cv == "leave-one-batch-out"
    assert typed.stages[-1].cv_accuracy is not None and typed.stages[-1].cv_accuracy > 0.9
    # and: the one training unit's evidence rides along, and only the training reading is validated
    assert list(typed.units) == [NOMINAL] and set(typed.confidence) == {"training"}
    assert all(s.temperatures == {} for s in typed.stages)
    assert any("cross-validated accuracy" in m for m in logs)


def test_one_angle_cannot_give_an_estimator(params: CuesParams) -> None:
    # given: training trials at one angle only
    train = {30.0: make_split(30, ["b1"], 3, seed=1)}
    # then: it says which angle has trials
    with pytest.raises(ValueError, match="only 30° has training trials"):
        fit_angle_estimator(train, params)


def test_angles_read_on_other_channels_cannot_give_an_estimator(params: CuesParams) -> None:
    # given: one angle recorded on a renamed channel
    train = {a: make_split(a, ["b1"], 3, seed=1) for a in (30.0, 45.0)}
    train[45.0] = train[45.0].rename(columns={"fsr3": "fsr4"})
    # then: it names both sets of channels
    with pytest.raises(ValueError, match="45° has channels"):
        fit_angle_estimator(train, params)


def test_without_an_estimator_the_reason_is_given_and_logged(params: CuesParams) -> None:
    # given: one angle
    logs: list[str] = []
    # when
    est, why = try_fit_angle_estimator({30.0: make_split(30, ["b1"], 3, seed=1)}, params, logs.append)
    # then: no estimator, a reason without the prefix, and a warning saying the cues fall back
    assert est is None and why is not None and why.startswith("it tells trained angles apart")
    assert any("fall back to the paper's profile method" in m for m in logs)


def test_one_batch_is_cross_validated_by_folds_of_trials(params: CuesParams) -> None:
    # given: every angle's trials in a single batch
    train = {float(a): make_split(a, ["b1"], 6, seed=3) for a in ANGLES}
    # when
    est = fit_angle_estimator(train, params)
    # then: nothing to leave out by batch, so 5 folds by trial
    assert est["cv"] == "5-fold by trial"
