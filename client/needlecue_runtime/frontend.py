"""The estimator's front end: the circuit that turns each FSR's resistance into the volts the rig
logs (batch.yaml `sensor.front_end`, docs/rig-log-format.md, "The front end").

A lab declares it; nothing assumes one where none is declared. The simulator's rigs are built from
the same models (`pipeline.sim.physics`), so the forward map (`volts_of`) and its inverse
(`resistance_of`, `conductance_us`) are one pair and cannot disagree. Numpy and pydantic only.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, TypeAdapter

MIN_KOHM = 0.01  # floor of an inverted resistance: a reading at the rail cannot be inverted further
MAX_KOHM = 1e6  # ceiling: an open FSR (over 10 MOhm) reads as this, not as infinity


class _Circuit(BaseModel):
    # A typo inside a declared circuit is an error, not metadata: it would change every feature.
    model_config = ConfigDict(frozen=True, extra="forbid")


class Divider(_Circuit):
    """A voltage divider: the FSR and a fixed resistor in series across `supply_v`, the output read
    across the fixed resistor (`fsr_at: supply`, the output rises with force) or across the FSR
    (`fsr_at: ground`, the output falls with force)."""

    circuit: Literal["divider"]
    supply_v: float = Field(gt=0, description="the supply across FSR and fixed resistor, V")
    fixed_kohm: float = Field(gt=0, description="the fixed resistor, kOhm")
    fsr_at: Literal["supply", "ground"] = Field(
        "supply", description="where the FSR sits: between supply and output, or output and ground"
    )
    series_kohm: float = Field(0.0, ge=0, description="resistance in series with the FSR's own, kOhm")


class Transimpedance(_Circuit):
    """An op-amp current-to-voltage converter (the FSR makers' recommended linear circuit): the FSR
    carries `drive_v` into the inverting input, `feedback_kohm` turns its current into the output,
    V = offset_v + drive_v * feedback_kohm / R: linear in the FSR's conductance."""

    circuit: Literal["transimpedance"]
    drive_v: float = Field(gt=0, description="magnitude of the voltage across the FSR, V")
    feedback_kohm: float = Field(gt=0, description="the feedback resistor, kOhm")
    offset_v: float = Field(0.0, description="output at zero conductance (a bias some designs add), V")
    series_kohm: float = Field(0.0, ge=0, description="resistance in series with the FSR's own, kOhm")


class Undeclared(_Circuit):
    """`circuit: none`: the lab says what it does not know; no feature may assume a circuit."""

    circuit: Literal["none"]


FrontEnd = Annotated[Divider | Transimpedance | Undeclared, Field(discriminator="circuit")]
Declared = Annotated[Divider | Transimpedance, Field(discriminator="circuit")]  # a circuit to read through
CIRCUITS = ("divider", "transimpedance", "none")  # the values of `circuit`
Circuit = Divider | Transimpedance


def is_declared(front_end: Divider | Transimpedance | Undeclared | None) -> bool:
    """Whether a front end says how volts come from resistance (a divider or a transimpedance)."""
    return isinstance(front_end, Divider | Transimpedance)


def declared(stored: dict | None) -> Circuit | None:
    """The circuit a stored `front_end` mapping (batch.json, front_ends.json, a model's inputs or a
    unit's calibration) declares; None for none or `circuit: none`. ValueError if malformed."""
    if stored is None:
        return None
    fe = _ADAPTER.validate_python(stored)
    return fe if is_declared(fe) else None


def legacy_divider(constants: Mapping[str, Any]) -> Divider:
    """The divider of a model or cue pack recorded before circuits were data: its params named the
    supply (`v_plus`), the fixed resistor (`r_m_kohm`) and the series term (`r_series_kohm`)."""
    return Divider(
        circuit="divider",
        supply_v=constants.get("v_plus", 5.0),
        fixed_kohm=constants.get("r_m_kohm", 10.0),
        series_kohm=constants.get("r_series_kohm", 0.0),
    )


def circuit_key(circuit: Circuit | None) -> str:
    """A circuit as one canonical string ("" for none): equal circuits, equal keys."""
    return "" if circuit is None else json.dumps(circuit.model_dump(mode="json"), sort_keys=True)


def volts_of(r_kohm: np.ndarray, fe: Circuit) -> np.ndarray:
    """Output volts for FSR resistances `r_kohm` (elementwise, before any rail or ADC clipping)."""
    return _output(np.asarray(r_kohm, dtype=np.float64) + fe.series_kohm, fe)


def volts_of_conductance(g_us: Any, fe: Circuit) -> Any:
    """Output volts for FSR conductances `g_us` (µS): `volts_of` of their resistance. Arithmetic only,
    so that it also runs on torch tensors (a unit's calibration is fitted through it)."""
    return _output(1e3 / g_us + fe.series_kohm, fe)


def _output(r: Any, fe: Circuit) -> Any:
    """The circuit's output for the total resistance `r` (kOhm) in the FSR's branch."""
    if isinstance(fe, Divider):  # written so that it rounds as the simulator always has
        if fe.fsr_at == "supply":
            return fe.supply_v / (1.0 + r / fe.fixed_kohm)
        return fe.supply_v / (1.0 + fe.fixed_kohm / r)
    return fe.offset_v + fe.drive_v * fe.feedback_kohm / r


def resistance_of(volts: np.ndarray, fe: Circuit) -> np.ndarray:
    """The FSR's resistance (kOhm, its series term taken out) behind output `volts`, the inverse of
    `volts_of`; readings at or past a rail give the nearest resistance the circuit can tell."""
    v = np.asarray(volts, dtype=np.float64)
    if isinstance(fe, Divider):
        eps = 1e-6 * fe.supply_v
        v = np.minimum(np.maximum(v, eps), fe.supply_v - eps)  # np.clip, without its ~4 µs wrapper
        ratio = fe.supply_v / v - 1.0  # R_total / fixed (supply side) or fixed / R_total (ground side)
        r = fe.fixed_kohm * ratio if fe.fsr_at == "supply" else fe.fixed_kohm / ratio
    else:
        above = np.maximum(v - fe.offset_v, 1e-9 * fe.drive_v)
        r = fe.drive_v * fe.feedback_kohm / above
    # the cue tracker calls this on every frame: ufuncs rather than np.clip's slower wrapper, same values
    return np.minimum(np.maximum(r - fe.series_kohm, MIN_KOHM), MAX_KOHM)


def conductance_us(volts: np.ndarray, fe: Circuit) -> np.ndarray:
    """The FSR's conductance (µS) behind output `volts`: above actuation it grows with the load."""
    return 1e3 / resistance_of(volts, fe)


def conductance_us_of_frame(volts: list[float], fe: Circuit) -> list[float]:
    """`conductance_us` of one frame's few readings, the same values: `resistance_of`'s arithmetic
    step for step on Python floats (IEEE, as numpy's). The cue tracker calls it on every frame, where
    numpy's cost per call on three values was 13 % of the cue scoring's time."""
    if isinstance(fe, Divider):
        supply, fixed = fe.supply_v, fe.fixed_kohm
        eps = 1e-6 * supply
        ratios = [supply / min(max(v, eps), supply - eps) - 1.0 for v in volts]
        rs = [fixed * q for q in ratios] if fe.fsr_at == "supply" else [fixed / q for q in ratios]
    else:
        gain, floor = fe.drive_v * fe.feedback_kohm, 1e-9 * fe.drive_v
        rs = [gain / max(v - fe.offset_v, floor) for v in volts]
    series = fe.series_kohm
    return [1e3 / min(max(r - series, MIN_KOHM), MAX_KOHM) for r in rs]


_ADAPTER: TypeAdapter[Divider | Transimpedance | Undeclared] = TypeAdapter(FrontEnd)
