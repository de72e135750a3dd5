"""Clock offset: recovered from the signals alone, within one estimator sample."""

from __future__ import annotations

import pytest

from pipeline.signals.clock import estimate_offset
from pipeline.signals.filters import SetAside
from tests.signals.fabricate import FSR_HZ, fabricate, volts_of


@pytest.mark.parametrize(
    ("offset_s", "n_channels"),
    [(0.23, 3), (-0.31, 3), (0.0, 3), (0.17, 1), (-0.12, 1), (0.36, 5), (-0.27, 5)],
)
def test_offset_is_recovered_within_one_fsr_sample(offset_s, n_channels):
    # Given a trial with a known clock offset and a nonlinear, lagged, quantised FSR response
    fab = fabricate(seed=abs(round(1000 * offset_s)) + n_channels, offset_s=offset_s, n_channels=n_channels)
    # When the offset is estimated from the signals alone
    est = estimate_offset(fab.t_ms / 1e3, volts_of(fab), fab.t_s, fab.force, 0.5, 0.002)
    # Then it is within one estimator sample period of the truth, with a clear fit
    assert abs(est.offset_s - offset_s) < 1.0 / FSR_HZ, est
    assert not est.on_edge
    assert 0.3 < est.quality <= 1.0


def test_too_little_overlap_is_set_aside():
    # Given a reference stream of only 0.4 s
    fab = fabricate(seed=6, offset_s=0.1)
    keep = fab.t_s < 0.4
    # When the offset is estimated, then the trial is set aside
    with pytest.raises(SetAside, match="overlap"):
        estimate_offset(fab.t_ms / 1e3, volts_of(fab), fab.t_s[keep], fab.force[keep], 0.5, 0.002)
