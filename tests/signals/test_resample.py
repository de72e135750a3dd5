"""One trial resampled: set aside outside the offset window, a uniform grid from zero, gaps dropped."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.signals.filters import SetAside
from pipeline.signals.resample import process_batch
from tests.signals.fabricate import (
    PARAMS,
    fabricate,
    resample_fab,
    resample_streams,
    volts_of,
    write_ingested,
)


def test_offset_outside_the_search_window_is_set_aside():
    # Given a clock offset larger than the search window
    fab = fabricate(seed=5, offset_s=0.45)
    narrow = PARAMS.model_copy(update={"max_offset_s": 0.2})
    # When the trial is resampled, then it is set aside as a shifted clock, not silently misaligned
    with pytest.raises(SetAside, match=r"shifted clock: .* offset of \+0\.4\d s .* within ±0.2 s"):
        resample_fab(fab, narrow)


def test_a_lone_trial_is_set_aside_on_evidence_not_for_its_quality(tmp_path):
    # Given batches of one trial: its estimator stream with another insertion's reference, the trial
    # as recorded, and its reference stamped 2 s late
    fab, other = fabricate(seed=11, offset_s=0.1), fabricate(seed=12, offset_s=-0.2)
    mismatched = fabricate(seed=11, offset_s=0.1)
    mismatched.t_s, mismatched.force = other.t_s, other.force
    late = fabricate(seed=11, offset_s=0.1)
    late.t_s = late.t_s + 2.0
    channels = ["fsr1", "fsr2", "fsr3"]
    statuses = {}
    for name, trial in {"mismatched": mismatched, "good": fab, "late": late}.items():
        folder = write_ingested(tmp_path, name, {"t1": trial}, channels=channels, with_truth=False)
        statuses[name] = process_batch(folder, PARAMS)[2][0]
    # When each is resampled, then the mismatched pair is kept: nothing to compare with shows the
    # files disagree (its low quality is the resample stage's flag)
    assert statuses["mismatched"]["status"] == "ok"
    assert float(statuses["mismatched"]["quality"]) < PARAMS.min_quality < float(statuses["good"]["quality"])
    # while its own reference 2 s late is named a shifted clock
    assert statuses["late"]["status"].startswith(
        "set aside: shifted clock: its own reference fits best at an offset of -1.9"
    )


@pytest.mark.parametrize("rate_hz", [30.0, 20.0])
def test_grid_is_uniform_at_rate_hz_and_starts_at_zero(rate_hz):
    # Given a fabricated trial
    fab = fabricate(seed=7, offset_s=-0.15, drop_p=0.0)
    # When it is resampled at rate_hz
    res = resample_fab(fab, PARAMS.model_copy(update={"rate_hz": rate_hz}))
    # Then t_s runs 0, 1/rate, 2/rate, ... and both streams are on it
    n = res.t_s.size
    np.testing.assert_array_equal(res.t_s, np.arange(n) / rate_hz)
    assert res.volts.shape == (n, 3) and res.force_n.shape == (n, 3)
    assert n >= (21.0 - 0.15 - 0.1) * rate_hz - 2


def test_grid_points_in_a_long_gap_are_dropped():
    # Given a trial whose estimator stream lost 0.6 s (8.0 - 8.6 s host time)
    fab = fabricate(seed=8, offset_s=0.05, drop_p=0.0)
    hole = (fab.t_ms >= 8000) & (fab.t_ms < 8600)
    fab.t_ms, fab.counts = fab.t_ms[~hole], fab.counts[~hole]
    # When it is resampled
    res = resample_fab(fab)
    # Then the grid points inside the gap are gone, and counted
    t_host = res.t_s + res.t0_host_s
    assert not np.any((t_host > 8.0) & (t_host < 8.59))
    assert 17 <= res.n_dropped_gap <= 20  # 0.63 s between the samples either side, at 30 Hz
    # And the 33 ms gaps of single dropped samples are not gaps
    fab2 = fabricate(seed=8, offset_s=0.05, drop_p=0.05)
    assert resample_fab(fab2).n_dropped_gap == 0


def test_an_estimator_stuck_at_rest_is_set_aside_for_that_not_for_its_clocks():
    # Given a trial whose estimator channels stayed at their rest reading through the insertion
    fab = fabricate(seed=5, offset_s=0.1)
    stuck = np.repeat(volts_of(fab)[:1], len(fab.t_ms), axis=0)
    stuck[::7, 0] += 5.0 / 1023  # one count of noise on one channel: not a flat line
    # When it is resampled, then the reason names the estimator, not the clock alignment
    with pytest.raises(SetAside, match=r"the estimator does not respond: its channels move at most 4\.9 mV"):
        resample_streams(fab.t_ms / 1e3, stuck, fab.t_s, fab.force, PARAMS)


def test_one_stuck_channel_is_named():
    # Given a trial whose second channel stayed at its rest reading (one count of noise) while the
    # others recorded the insertion
    fab = fabricate(seed=5, offset_s=0.1)
    volts = volts_of(fab).copy()
    volts[:, 1] = volts[0, 1]
    volts[::5, 1] += 5.0 / 1023
    # When it is resampled, then that channel is named as stuck
    with pytest.raises(SetAside, match=r"channel 2 does not respond: moves at most 4\.9 mV while another"):
        resample_streams(fab.t_ms / 1e3, volts, fab.t_s, fab.force, PARAMS)
