"""Raw units to physical ones: estimator ADC counts to volts, reference mN to N
(`docs/rig-log-format.md`, "Units and clocks")."""

from __future__ import annotations

import numpy as np


def to_volts(values: np.ndarray, units: str, adc_bits: int | None, vref_v: float | None) -> np.ndarray:
    """Estimator samples in volts: ADC counts scale by vref / (2^bits - 1)."""
    values = np.asarray(values, dtype=np.float64)
    if units == "volts":
        return values
    if units == "counts":
        if adc_bits is None or vref_v is None:
            raise ValueError("units 'counts' need adc_bits and vref_v")
        return values * (float(vref_v) / (2 ** int(adc_bits) - 1))
    raise ValueError(f"unknown sensor units {units!r} (expected 'counts' or 'volts')")


def to_newtons(values: np.ndarray, units: str) -> np.ndarray:
    """Reference forces in N."""
    values = np.asarray(values, dtype=np.float64)
    if units == "N":
        return values
    if units == "mN":
        return values * 1e-3
    raise ValueError(f"unknown reference units {units!r} (expected 'N' or 'mN')")
