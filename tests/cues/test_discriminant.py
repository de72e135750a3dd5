"""One evidence stage of the angle estimator: the shrunk scatter, the template weight, the units'
offset spread, and the bound past which a trial lies outside what training covered."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.config import CuesParams
from pipeline.cues.discriminant import (
    MIN_UNITS_FOR_SPREAD,
    fit_stage,
    offset_spread,
    outside_limit,
    stage_logits,
)


def _cells(units: int, classes: int = 3, per_cell: int = 6, seed: int = 0, departure: float = 0.0) -> tuple:
    """Trials of 2 features around class means 3 apart, each unit shifted by its own offset and, with
    `departure`, each of its classes by its own extra amount; scatter 0.3."""
    rng = np.random.default_rng(seed)
    x, y, u = [], [], []
    for k in range(units):
        offset = rng.normal(0, 1.0, 2)
        for c in range(classes):
            own = rng.normal(0, departure, 2)
            for _ in range(per_cell):
                x.append(np.array([3.0 * c, -1.5 * c]) + offset + own + rng.normal(0, 0.3, 2))
                y.append(c)
                u.append(f"u{k}")
    return np.array(x), np.array(y), np.array(u)


def test_a_stage_finds_the_average_unit_s_class_means_and_the_trial_scatter() -> None:
    # given: three units' trials of three classes
    x, y, u = _cells(3)
    # when
    fitted = fit_stage(x, y, u, 3, CuesParams(lda_shrinkage=0.0), "stage 0")
    stage = fitted["stage"]
    # then: the class means step as the data do (offsets are centred, so differences are what is
    # identified), the precision is the inverse of a 0.3 scatter, and every (unit, class) is a cell
    steps = np.diff(stage["means"], axis=0)
    assert steps == pytest.approx(np.array([[3.0, -1.5], [3.0, -1.5]]), abs=0.15)
    assert np.diag(np.linalg.inv(stage["precision"])) == pytest.approx([0.09, 0.09], rel=0.35)
    assert len(fitted["cells"]) == 9 and all(n == 6 for n, _ in fitted["cells"].values())


def test_units_that_depart_at_an_angle_get_a_smaller_template_weight() -> None:
    # given: units that only shift, and units that also depart from the layout at each class
    params = CuesParams(lda_shrinkage=0.0)
    shifting = fit_stage(*_cells(4, seed=1), 3, params, "s")["stage"]["template_weight"]
    departing = fit_stage(*_cells(4, seed=1, departure=1.0), 3, params, "s")["stage"]["template_weight"]
    # then: the departures weigh: fewer trials of a unit count as much as the average unit's means
    assert departing is not None
    assert shifting is None or shifting > departing


def test_the_offset_spread_needs_enough_units() -> None:
    # given: the offsets of too few units, and of enough
    precision = np.eye(2)
    few = {f"u{k}": np.array([k, -k], dtype=float) for k in range(MIN_UNITS_FOR_SPREAD - 1)}
    enough = {"a": np.array([1.0, 0.0]), "b": np.array([-1.0, 0.0]), "c": np.array([0.0, 0.0])}
    # then: none bounds a new unit from too few; from enough, their variance per feature
    assert offset_spread(few, precision) is None
    assert offset_spread(enough, precision) == pytest.approx((1 + 1 + 0) / (2 * 2))


def test_one_trial_per_unit_and_class_says_nothing_shows_the_scatter() -> None:
    # given: one trial per (unit, class)
    x, y, u = _cells(2, per_cell=1)
    # then: the fit refuses, saying where and why
    with pytest.raises(ValueError, match=r"stage 3: .*nothing shows how trials scatter"):
        fit_stage(x, y, u, 3, CuesParams(), "stage 3")


def test_a_stage_reads_each_trial_through_its_own_unit() -> None:
    # given: a stage fitted on three units
    x, y, u = _cells(3, seed=4)
    fitted = fit_stage(x, y, u, 3, CuesParams(lda_shrinkage=0.0), "s")
    # when: the trials are scored
    z = stage_logits(fitted, x, u, 3)
    # then: each trial scores highest at its own class
    assert (np.argmax(z, axis=1) == y).mean() == 1.0


def test_the_outside_bound_widens_as_trials_get_fewer_and_is_none_when_too_few() -> None:
    # then: fewer trials, a wider bound (Hotelling), and none when there are no degrees of freedom
    many, few = outside_limit(600, 6, 9), outside_limit(40, 6, 9)
    assert many is not None and few is not None and few > many > 9
    assert outside_limit(14, 6, 9) is None
