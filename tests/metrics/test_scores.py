"""The paper's error measures, eq. (3)-(4), and the angle-gap summaries."""

from __future__ import annotations

import math

import numpy as np
import pytest

from needlecue_runtime.vocab import AXES
from pipeline.metrics.scores import axis_scores, gap_summary, nrmse_pct, rmse
from tests.metrics.fakes import ANGLES, AXIS_SCALE, gap_error


def test_rmse_and_nrmse_match_hand_computed_values():
    # given one axis where only the last sample is off by 2 over a reference range of 4
    pred, ref = np.array([1.0, 2.0, 3.0]), np.array([1.0, 2.0, 5.0])
    # when scored, then RMSE = sqrt(4/3) and NRMSE = 100 * RMSE / 4
    assert rmse(pred, ref) == pytest.approx(math.sqrt(4 / 3))
    assert nrmse_pct(pred, ref) == pytest.approx(100 * math.sqrt(4 / 3) / 4)


def test_scores_are_per_axis():
    # given three axes: the case above, an all-zero prediction of 0, 1, 2, and a perfect one
    pred = np.array([[1.0, 0.0, 7.0], [2.0, 0.0, 8.0], [3.0, 0.0, 9.0]])
    ref = np.array([[1.0, 0.0, 7.0], [2.0, 1.0, 8.0], [5.0, 2.0, 9.0]])
    # when scored
    s = axis_scores(pred, ref)
    # then each axis has its own RMSE and range
    assert s["fx"]["rmse"] == pytest.approx(math.sqrt(4 / 3))
    assert s["fx"]["nrmse_pct"] == pytest.approx(100 * math.sqrt(4 / 3) / 4)
    assert s["fy"]["rmse"] == pytest.approx(math.sqrt(5 / 3))
    assert s["fy"]["nrmse_pct"] == pytest.approx(100 * math.sqrt(5 / 3) / 2)
    assert s["fz"] == {"rmse": 0.0, "nrmse_pct": 0.0}


def test_constant_reference_has_no_nrmse_and_shapes_must_match():
    assert math.isnan(float(nrmse_pct(np.array([1.0, 2.0]), np.array([3.0, 3.0]))))
    with pytest.raises(ValueError, match="shape"):
        rmse(np.zeros((3, 3)), np.zeros((4, 3)))


def test_gap_summary_averages_exactly_the_pairs_with_that_gap():
    # given a matrix whose NRMSE is 100 * gap_error (reference range 1 N)
    matrix = {
        t: {
            d: dict(zip(AXES, 100 * gap_error("fnn", float(t), float(d)) * AXIS_SCALE, strict=True))
            for d in ANGLES
        }
        for t in ANGLES
    }
    # when summarised per gap
    s15, n15 = gap_summary(matrix, 15)
    s30, n30 = gap_summary(matrix, 30)
    s45, n45 = gap_summary(matrix, 45)
    # then: 15° pairs (0,15) (15,0) (15,30) (30,15) (30,45) (45,30) -> 10 + 0.1 * mean train index
    assert n15 == 6 and s15["fx"] == pytest.approx((10 + 10.1 + 10.1 + 10.2 + 10.2 + 10.3) / 6)
    assert n30 == 4 and s30["fx"] == pytest.approx((20 + 20.2 + 20.1 + 20.3) / 4)
    assert n45 == 2 and s45["fx"] == pytest.approx((30 + 30.3) / 2)
    assert s15["fz"] == pytest.approx(3 * s15["fx"])
    assert gap_summary(matrix, 60) == ({}, 0)
