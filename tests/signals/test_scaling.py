"""Units: ADC counts to volts, mN to N."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.signals.scaling import to_newtons, to_volts


def test_counts_become_volts_and_millinewtons_become_newtons():
    # Given 10-bit counts over a 5 V reference, and forces in mN
    counts = np.array([0.0, 511.5, 1023.0])
    # When converted
    volts = to_volts(counts, "counts", 10, 5.0)
    newtons = to_newtons(np.array([250.0, -1000.0]), "mN")
    # Then full scale is vref, volts and N pass through unchanged
    np.testing.assert_allclose(volts, [0.0, 2.5, 5.0])
    np.testing.assert_allclose(newtons, [0.25, -1.0])
    np.testing.assert_array_equal(to_volts(volts, "volts", None, None), volts)
    np.testing.assert_array_equal(to_newtons(newtons, "N"), newtons)
    with pytest.raises(ValueError):
        to_volts(counts, "counts", None, 5.0)
    with pytest.raises(ValueError):
        to_newtons(newtons, "kN")
