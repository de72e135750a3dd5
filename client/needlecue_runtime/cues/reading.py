"""How the angle estimator reads one estimator unit: its class means, how sure we are of them, and
the posterior over the trained angles they give.

Per evidence stage, a trial's features are modelled as

    the angle's mean for the average unit + the unit's offset + the unit's own departure at that angle
    + the trial's scatter (one covariance, shared by every unit and angle)

(`pipeline.cues.unit_evidence` fits the average unit; docs/units.md). A unit is known by its *cells*: per
angle, how many of its trials reached the stage and their mean features (its training trials, or a
new unit's calibration insertions). `read_unit` turns the cells into the unit's class means and the
variance left in them; `log_scores` scores a trial's features with both, so that a unit whose means
are uncertain (an uncalibrated unit, one calibration insertion) gets a flatter posterior instead of
a confident wrong one. Variances are per feature in the scatter's whitened units (1 = one trial's
scatter). Numpy only: the simulator's client imports this module.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property

import numpy as np

Cell = tuple[int, float, np.ndarray]  # one class of a unit: (class, its trials n, their mean features)


@dataclass(frozen=True)
class UnitReading:
    """A unit's class means (classes, features) and, per class, the variance of the unit's class
    mean beyond the trial scatter (whitened units per feature; inf: nothing bounds it)."""

    means: np.ndarray
    extra_var: np.ndarray
    departs: bool = False  # its cells sit unlike any shift of the training units' means (`departs`)

    @cached_property  # the tracker asks on every frame
    def known(self) -> bool:
        """Whether anything bounds where this unit's classes lie."""
        return bool(np.isfinite(self.extra_var).all())


def own_departure(mu: np.ndarray, cells: Sequence[Cell], precision: np.ndarray | None) -> float:
    """The variance of a unit's own departures at an angle (whitened units per feature) as its cells
    show it: how far they sit from the average unit's means once shifted by their mean difference,
    beyond their trials' scatter (C cells have C - 1 degrees of freedom per feature around their
    mean shift); 0 when they fit a shift, or with fewer than two cells or no precision."""
    if precision is None or len(cells) < 2:
        return 0.0
    mu = np.asarray(mu, dtype=np.float64)
    shift = np.mean([m - mu[c] for c, _, m in cells], axis=0)
    squares = sum(float((r := m - mu[c] - shift) @ precision @ r) for c, _, m in cells) / mu.shape[1]
    scatter = (1.0 - 1.0 / len(cells)) * sum(1.0 / n for _, n, _ in cells)
    return max((squares - scatter) / (len(cells) - 1), 0.0)


def neighbour_distance(mu: np.ndarray, precision: np.ndarray) -> float:
    """The median squared distance between neighbouring trained angles' means (classes in angle
    order), whitened, per feature: how far a class may move before it reaches the next angle's."""
    step = np.diff(np.asarray(mu, dtype=np.float64), axis=0)
    return float(np.median(np.einsum("cf,fg,cg->c", step, precision, step))) / step.shape[1]


def departs(mu: np.ndarray, cells: Sequence[Cell], precision: np.ndarray | None) -> bool:
    """Whether a unit's own departures (`own_departure`) are as large as the distance between
    neighbouring trained angles: its classes are then not laid out as training saw them (a turned
    connector; another FSR law), its insertions could stand in another order, and how its trials
    scatter around them is unknown, so nothing it shows at this stage is validated. Not net of the
    training units' own departures (1/k): on `power-law`, whose training units depart about as far,
    that let a new unit end 4.4 % of its insertions on a wrong cue (0.4 % as it is)."""
    return precision is not None and own_departure(mu, cells, precision) > neighbour_distance(mu, precision)


def read_unit(
    mu: np.ndarray,
    cells: Sequence[Cell],
    k: float | None,
    spread: float | None,
    precision: np.ndarray | None = None,
) -> UnitReading:
    """A unit's reading from the average unit's `mu` (classes, features) and the unit's `cells`
    [(class, trials n, their mean features)], with the stage's template weight `k` (the scatter's
    variance over that of a unit's own departures at an angle; None: departures not told from
    scatter) and `spread` (the variance of the training units' offsets; None: one training unit,
    nothing says how far a unit may sit from the average).

    1. Shift: mu moves by the unit's offset, the cells' mean difference from mu. Its noise is
       e = sum(1/n + 1/k) / cells²; the shift is shrunk by spread / (spread + e) towards zero (no
       spread known: a flat prior, the full shift). What is left of the offset's variance is
       spread·e / (spread + e) (e without a spread; the spread without cells; inf with neither).
    2. Pull: each cell's class moves towards its trials, (n·trials + k·shifted) / (n + k), and its
       variance becomes that of the two combined (k None: no pull, the shift alone).

    With the stage's `precision` (a unit training did not see), the reading also says whether the
    unit `departs`: its calibration insertions sit so far from every shift of the training units'
    layout (a turned connector, another FSR law) that its classes could have moved past their
    neighbours. Widening such a unit's uncertainty by its own departure instead was measured and
    not kept (docs/units.md).
    """
    mu = np.asarray(mu, dtype=np.float64)
    away = departs(mu, cells, precision)
    tau2 = 0.0 if k is None else 1.0 / k
    if not cells:
        v_off = math.inf if spread is None else float(spread)
        return UnitReading(mu, np.full(len(mu), v_off + tau2))
    shift = np.mean([m - mu[c] for c, _, m in cells], axis=0)
    noise = sum(1.0 / n + tau2 for _, n, _ in cells) / len(cells) ** 2
    shrink = 1.0 if spread is None else spread / (spread + noise)
    v_off = noise if spread is None else spread * noise / (spread + noise)
    means = mu + shrink * shift
    var = np.full(len(mu), v_off + tau2)
    if k is not None:
        for c, n, m in cells:
            means[c] = (n * m + k * means[c]) / (n + k)
            var[c] = 1.0 / (n + 1.0 / var[c])
    return UnitReading(means, var, away)


def distances(precision: np.ndarray, means: np.ndarray, x: np.ndarray) -> np.ndarray:
    """(classes,) squared Mahalanobis distances of features `x` from each class mean."""
    d = np.asarray(x, dtype=np.float64)[None, : means.shape[1]] - means
    return np.einsum("cf,fg,cg->c", d, precision, d)


def log_scores(d2: np.ndarray, reading: UnitReading, temperature: float) -> np.ndarray:
    """(classes,) log posterior scores (up to a constant; equal priors) of a trial whose squared
    distances from the unit's class means are `d2`: Gaussian, with each class's covariance the
    scatter's times (1 + its extra variance), over the stage's temperature. All zero (a flat
    posterior) when nothing bounds the unit's means."""
    if not reading.known:
        return np.zeros(len(d2))
    scale = 1.0 + reading.extra_var
    width = reading.means.shape[1]
    return (-0.5 * d2 / scale - 0.5 * width * np.log(scale)) / temperature


def outside(d2: np.ndarray, reading: UnitReading, temperature: float, limit: float | None) -> bool:
    """Whether the features lie outside what training covered: further from every class mean, on the
    calibrated scatter, than `limit` (the stage's `outside_limit`, None: no test). The scatter is
    widened by the temperature where cross-validation found it too narrow (a temperature under 1
    sharpens well separated classes, it does not narrow the scatter) and by the unit's uncertainty."""
    if limit is None or not reading.known:
        return False
    return bool(np.min(d2 / (max(temperature, 1.0) * (1.0 + reading.extra_var))) > limit)
