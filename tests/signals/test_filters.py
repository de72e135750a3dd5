"""Filters: the anti-alias low-pass and the gap mask."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.signals.filters import gap_mask, resample_stream


def _amplitude(t: np.ndarray, x: np.ndarray, hz: float) -> float:
    """Amplitude of the `hz` component of x(t), by least squares on sin/cos (+ mean)."""
    design = np.stack([np.sin(2 * np.pi * hz * t), np.cos(2 * np.pi * hz * t), np.ones_like(t)], axis=1)
    coef, *_ = np.linalg.lstsq(design, x, rcond=None)
    return float(np.hypot(coef[0], coef[1]))


def test_anti_alias_filter_removes_a_tone_above_the_target_nyquist():
    # Given a 100 Hz stream: a slow 0.5 Hz signal plus a 20 Hz tone (above 15 Hz, the 30 Hz grid's Nyquist)
    t = np.arange(0.0, 20.0, 0.01)
    x = np.sin(2 * np.pi * 0.5 * t) + 0.5 * np.sin(2 * np.pi * 20.0 * t)
    grid = np.arange(2.0, 18.0, 1.0 / 30.0)
    # When it is resampled onto the 30 Hz grid with, and naively without, the anti-alias filter
    filtered = resample_stream(t, x, grid, 30.0, 4)
    naive = np.interp(grid, t, x)
    # Then naive decimation folds the tone to 10 Hz; the filtered stream keeps almost none of it
    alias_naive, alias_filtered = _amplitude(grid, naive, 10.0), _amplitude(grid, filtered, 10.0)
    assert alias_naive > 0.3
    assert alias_filtered < 0.02
    # And the slow signal passes unchanged
    assert _amplitude(grid, filtered, 0.5) == pytest.approx(1.0, abs=0.01)


def test_gap_mask_marks_only_points_inside_long_gaps():
    # Given samples with a 0.5 s hole and a 0.1 s hole
    t_src = np.array([0.0, 0.1, 0.2, 0.7, 0.8, 0.9])
    query = np.array([0.15, 0.2, 0.3, 0.5, 0.7, 0.75])
    # When the gap mask is computed for max_gap 0.25 s
    mask = gap_mask(t_src, query, 0.25)
    # Then only the points strictly inside the 0.5 s hole are in a gap
    np.testing.assert_array_equal(mask, [False, False, True, True, False, False])
