"""How the angle estimator reads one unit: class means shifted and pulled by the unit's cells, the
uncertainty left in them, and the posterior and the "outside" test that use it."""

from __future__ import annotations

import math

import numpy as np
import pytest

from needlecue_runtime.cues.reading import (
    departs,
    distances,
    log_scores,
    neighbour_distance,
    outside,
    own_departure,
    read_unit,
)
from pipeline.cues.discriminant import outside_limit

MU = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])


def test_a_unit_without_cells_is_the_average_unit_with_the_units_spread_around_it() -> None:
    # given / when: no cells, an offset spread of 1 and a template weight of 2
    r = read_unit(MU, [], 2.0, 1.0)
    # then: the average unit's means, uncertain by the spread plus a unit's departure (1/k)
    np.testing.assert_array_equal(r.means, MU)
    np.testing.assert_allclose(r.extra_var, [1.5, 1.5, 1.5])
    assert r.known


def test_with_one_training_unit_an_uncalibrated_unit_is_not_known() -> None:
    # given / when: no spread (one training unit) and no cells
    r = read_unit(MU, [], None, None)
    # then: nothing bounds its means: the posterior is flat, and no "outside" verdict either
    assert not r.known and math.isinf(r.extra_var[0])
    np.testing.assert_array_equal(log_scores(np.array([0.0, 5.0, 9.0]), r, 1.0), np.zeros(3))
    assert not outside(np.array([1e9, 1e9, 1e9]), r, 1.0, 10.0)


def test_a_well_measured_offset_shifts_every_class() -> None:
    # given: many trials at two of three angles, all sitting 0.5 off the average unit
    d = np.array([0.5, -0.5])
    cells = [(0, 1e6, MU[0] + d), (2, 1e6, MU[2] + d)]
    # when: no pull (k None), a wide offset spread
    r = read_unit(MU, cells, None, 1e6)
    # then: every class moves by the offset, the angle without trials too, and is now certain
    np.testing.assert_allclose(r.means, MU + d, atol=1e-6)
    assert np.all(r.extra_var < 1e-5)


def test_offset_is_shrunk_by_how_well_few_trials_pin_it_down() -> None:
    # given: one trial at one angle (its variance 1/n = 1) and an offset spread of 1
    cells = [(1, 1.0, MU[1] + np.array([1.0, 0.0]))]
    # when / then: half the offset (spread / (spread + variance)), half the variance left
    r = read_unit(MU, cells, None, 1.0)
    np.testing.assert_allclose(r.means[0], [0.5, 0.0])
    np.testing.assert_allclose(r.extra_var, [0.5, 0.5, 0.5])
    # and with no spread known (one training unit): a flat prior, the full shift, its noise left
    flat = read_unit(MU, cells, None, None)
    np.testing.assert_allclose(flat.means[0], [1.0, 0.0])
    np.testing.assert_allclose(flat.extra_var, [1.0, 1.0, 1.0])


def test_a_unit_s_trials_pull_their_class_by_count_against_the_weight() -> None:
    # given: one trial at angle 0 sitting at the average unit's mean 0 + (3, 3), k = 2, a huge spread
    cells = [(0, 1.0, np.array([3.0, 3.0]))]
    r = read_unit(MU, cells, 2.0, 1e12)
    # then: the shift takes the whole difference (the only cell), so the pull changes nothing more;
    # every class moved by (3, 3), and the cell's class is the surest
    np.testing.assert_allclose(r.means, MU + 3.0, atol=1e-6)
    assert r.extra_var[0] < r.extra_var[1] == r.extra_var[2]


def test_log_scores_are_the_gaussian_log_posterior_up_to_a_constant() -> None:
    # given: class means, a shared precision, and a unit whose means are certain
    rng = np.random.default_rng(0)
    means = rng.normal(0, 1, (3, 4))
    a = rng.normal(0, 1, (4, 4))
    precision = a @ a.T + 4 * np.eye(4)
    r = read_unit(means, [(c, 1e12, means[c]) for c in range(3)], None, 1e12)
    for x in rng.normal(0, 1, (5, 4)):
        # when: scored as the tracker scores them, at temperature 2
        z = log_scores(distances(precision, r.means, x), r, 2.0)
        # then: -1/2 Mahalanobis distance over the temperature, plus one constant
        d = x - means
        logp = -0.25 * np.einsum("ci,ij,cj->c", d, precision, d)
        np.testing.assert_allclose(z - logp, np.full(3, (z - logp)[0]), atol=1e-6)


def test_uncertain_means_flatten_the_posterior() -> None:
    # given: a trial nearest class 0
    d2 = np.array([0.5, 4.0, 9.0])
    sure = read_unit(MU, [(c, 1e12, MU[c]) for c in range(3)], None, 1e12)
    unsure = read_unit(MU, [], None, 3.0)  # an uncalibrated unit among units spread by 3
    # when / then: the same ranking, but a smaller lead
    a, b = log_scores(d2, sure, 1.0), log_scores(d2, unsure, 1.0)
    assert np.argmax(a) == np.argmax(b) == 0
    assert (a[0] - a[1]) > (b[0] - b[1]) > 0


def test_a_trial_far_from_every_class_is_outside_what_training_covered() -> None:
    # given: a unit known exactly, and a limit of 13.8 on the squared distance
    r = read_unit(MU, [(c, 1e12, MU[c]) for c in range(3)], None, 1e12)
    # when / then: nearer than the limit to some class is inside, further from all is outside
    assert not outside(np.array([2.0, 5.0, 12.0]), r, 1.0, 13.8)
    assert outside(np.array([20.0, 25.0, 30.0]), r, 1.0, 13.8)
    # a temperature over 1 (the scatter found too narrow) widens what counts as inside, one under 1
    # does not narrow it; and without a limit (too few trials to say) nothing is outside
    assert not outside(np.array([20.0, 25.0, 30.0]), r, 2.0, 13.8)
    assert not outside(np.array([2.0, 5.0, 12.0]), r, 0.2, 13.8)
    assert not outside(np.array([1e9, 1e9, 1e9]), r, 1.0, None)


def test_the_outside_limit_widens_with_fewer_trials_and_goes_when_too_few() -> None:
    # given: 30 features, 6 angles
    # when / then: many trials: near the chi-square 0.999 quantile of 30 (59.7); fewer: wider; too few: none
    many = outside_limit(100_000, 6, 30)
    assert many is not None and 59 < many < 61
    assert outside_limit(162, 6, 30) > many
    assert outside_limit(54, 6, 30) > outside_limit(162, 6, 30)
    assert outside_limit(30, 6, 30) is None


def test_a_new_unit_laid_out_as_a_shift_of_the_training_units_does_not_depart() -> None:
    # given: one calibration insertion per angle, each the average unit's mean shifted by (2, -1)
    # plus a small scatter, and the scatter's precision (identity)
    noise = np.array([[0.3, -0.2], [-0.1, 0.4], [-0.2, -0.2]])
    cells = [(c, 1.0, MU[c] + np.array([2.0, -1.0]) + noise[c]) for c in range(3)]
    # when: read as a unit training did not see, with one training unit (k and spread None)
    r = read_unit(MU, cells, None, None, np.eye(2))
    # then: its own departures are within scatter: it does not depart, and the shift reads it
    assert own_departure(MU, cells, np.eye(2)) == 0.0
    assert not r.departs
    np.testing.assert_allclose(r.means, MU + np.array([2.0, -1.0]) + noise.mean(axis=0))


def test_a_new_unit_laid_out_unlike_any_training_unit_departs() -> None:
    # given: calibration insertions whose classes are swapped around against the average unit's
    # (a turned connector), 1 trial each, far beyond the scatter (identity precision)
    layout = np.array([[8.0, 0.0], [0.0, 8.0], [0.0, 0.0]])
    cells = [(c, 1.0, layout[c]) for c in range(3)]
    # when: read as a new unit, and as a training unit is (no precision)
    new = read_unit(MU, cells, None, None, np.eye(2))
    trained = read_unit(MU, cells, None, None)
    # then: a departure far beyond the neighbouring angles' distance: the new unit departs; the
    # training reading is not tested; both read the same means
    assert own_departure(MU, cells, np.eye(2)) > 10.0 * neighbour_distance(MU, np.eye(2))
    assert new.departs and not trained.departs
    np.testing.assert_array_equal(new.means, trained.means)


def test_a_unit_departs_when_its_classes_could_have_moved_past_their_neighbours() -> None:
    # given: six angles 1 apart in each of 5 features (a squared step of 1 per feature, whitened),
    # and units departing from a shift at each angle by a standard deviation of 0.5 and of 2
    rng = np.random.default_rng(3)
    mu = np.cumsum(np.ones((6, 5)), axis=0)
    assert neighbour_distance(mu, np.eye(5)) == pytest.approx(1.0)
    near = [(c, 1e6, mu[c] + rng.normal(0, 0.5, 5)) for c in range(6)]
    far = [(c, 1e6, mu[c] + rng.normal(0, 2.0, 5)) for c in range(6)]
    # when / then: departures of about 0.25 per feature keep the layout; of about 4, they do not
    assert not departs(mu, near, np.eye(5))
    assert departs(mu, far, np.eye(5))
    # and a training unit's reading (no precision) is never tested
    assert not departs(mu, far, None)
