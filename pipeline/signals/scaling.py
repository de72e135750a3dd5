"""Raw units to physical ones: estimator ADC counts to volts, reference forces to N
(`docs/rig-log-format.md`, "Units and clocks")."""

from __future__ import annotations

import numpy as np

from pipeline.rig.format import NEWTONS_PER_UNIT


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
    """Reference forces in N, from batch.yaml's `reference.units` (`rig.format.NEWTONS_PER_UNIT`: N,
    mN, g and kg of force, lbf)."""
    values = np.asarray(values, dtype=np.float64)
    if units == "N":
        return values
    if units not in NEWTONS_PER_UNIT:
        allowed = ", ".join(repr(u) for u in NEWTONS_PER_UNIT)
        raise ValueError(f"unknown reference units {units!r} (reference.units is one of {allowed})")
    return values * NEWTONS_PER_UNIT[units]
