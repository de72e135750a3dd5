"""The model's inputs computed from the estimator's volts, and a unit's affine map on them.

Every estimator unit differs (docs/physics.md, "Estimator units"): each FSR's cast-in preload sets
its rest reading, its part-to-part gain scales its response, and the tripod's placement mixes the
lateral force differently. Raw volts carry all of that into the weights. The kinds here take out
what physics says is unit-specific and leaves the rest linear:

- `volts`: the front end's output as read (the paper's input);
- `rest_volts`: volts minus the trial's rest reading (removes most of the preload);
- `conductance`: the FSR conductance (µS) behind the volts, through the estimator's own circuit
  (batch.yaml `sensor.front_end`, `needlecue_runtime.frontend`); above actuation it grows with the load;
- `rest_conductance`: conductance minus the trial's rest conductance: the load added by the needle,
  times each FSR's gain. The preload drops out; gain and placement are left as a linear map per
  unit, which is what a unit's calibration (`InputTransform`) fits.

The conductance kinds need a circuit, and take it from the data, never from params: a model records
the one its training units declared (`ModelInputs.front_end`), and a unit that declares its own is
read through that. With no circuit declared, only the volts kinds exist.

The rest reading is causal and raw: the mean of the volts a trial reads in its first `rest_s`
seconds (the running mean until then), before any calibration or conductance. A relative input is
the input of the reading minus the input of the rest reading, the same numbers in training, in batch
prediction and in the deployed graph (`pipeline.modelling.export`, fed by `RestReading`), so a
simulator in any language needs nothing but the volts and their running mean. Numpy and pydantic
only: the simulator's client imports this module.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Literal, get_args

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from needlecue_runtime.frontend import (
    Declared,
    Divider,
    Transimpedance,
    conductance_us,
    legacy_divider,
    volts_of_conductance,
)
from needlecue_runtime.params import InputParams

INPUT_KINDS: tuple[str, ...] = tuple(
    k for k in get_args(InputParams.model_fields["kind"].annotation) if k != "auto"
)
NEEDS_CIRCUIT = ("conductance", "rest_conductance")
# keys of the inputs that models recorded before the circuit was data (a divider from params)
LEGACY_DIVIDER = ("v_plus", "r_m_kohm", "r_series_kohm", "r_open_kohm")


class ModelInputs(BaseModel):
    """What a model computes from the volts: the params' `kind` and `rest_s`, and the circuit
    (`front_end`) its training units declared, which the conductance kinds read through."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    kind: Literal["volts", "rest_volts", "conductance", "rest_conductance"] = "volts"
    rest_s: float = Field(0.5, gt=0)
    front_end: Declared | None = None

    @model_validator(mode="after")
    def _circuit_if_needed(self) -> ModelInputs:
        if self.kind in NEEDS_CIRCUIT and self.front_end is None:
            raise ValueError(
                f"inputs kind {self.kind!r} reads the FSRs' conductance, which needs the estimator's "
                "front end, and none is declared (batch.yaml sensor.front_end, docs/rig-log-format.md "
                "§3a); declare it, or use inputs kind volts or rest_volts"
            )
        return self

    @property
    def needs_circuit(self) -> bool:
        return self.kind in NEEDS_CIRCUIT

    def through(self, front_end: Divider | Transimpedance | None) -> ModelInputs:
        """The same inputs read through another unit's circuit (None: keep this one)."""
        if front_end is None or not self.needs_circuit:
            return self
        return self.model_copy(update={"front_end": front_end})


def inputs_for(kind: str, rest_s: float, front_end: Divider | Transimpedance | None) -> ModelInputs:
    """The inputs a model trains on: `kind` (chosen or pinned), through the training units' circuit
    if it reads one (ValueError, saying what to declare, when it needs one and there is none)."""
    if kind not in INPUT_KINDS:
        raise ValueError(f"inputs kind {kind!r} is not one of {', '.join(INPUT_KINDS)}")
    return ModelInputs(kind=kind, rest_s=rest_s, front_end=front_end if kind in NEEDS_CIRCUIT else None)


def spec_of(stored: Mapping[str, Any] | None) -> ModelInputs:
    """The inputs a checkpoint or deployable model records, checked (an unknown setting or kind is a
    ValueError); None, a model from before inputs were recorded, reads raw volts. A model recorded
    before the circuit was data carries its divider's constants: they become its front end."""
    if stored is None:
        return ModelInputs()
    d = dict(stored)
    legacy = {k: d.pop(k) for k in LEGACY_DIVIDER if k in d}
    if legacy and d.get("front_end") is None and d.get("kind") in NEEDS_CIRCUIT:
        d["front_end"] = legacy_divider(legacy).model_dump(mode="json")
    return ModelInputs.model_validate(d)


def _relative(spec: ModelInputs) -> bool:
    """Whether the inputs are relative to the trial's rest reading."""
    return spec.kind.startswith("rest_")


def _absolute(volts: np.ndarray, spec: ModelInputs) -> np.ndarray:
    volts = np.asarray(volts, dtype=np.float64)
    if spec.front_end is not None and spec.needs_circuit:
        return conductance_us(volts, spec.front_end)
    return volts


def rest_reading(values: np.ndarray, codes: np.ndarray, t: np.ndarray, rest_s: float) -> np.ndarray:
    """Per row, its trial's rest reading so far: the running mean of the trial's rows (in time
    order) within `rest_s` of its first row, frozen after. Rows keep their given order."""
    values = np.asarray(values, dtype=np.float64)
    out = np.empty_like(values)
    order = np.lexsort((t, codes))
    c = codes[order]
    cuts = np.flatnonzero(c[1:] != c[:-1]) + 1
    for rows in np.split(order, cuts):
        if len(rows) == 0:
            continue
        tt = t[rows]
        resting = tt - tt[0] < rest_s - 1e-9
        n_rest = int(np.argmin(resting)) if not resting.all() else len(rows)  # a prefix: t is sorted
        v = values[rows]
        running = np.cumsum(v[:n_rest], axis=0) / np.arange(1, n_rest + 1)[:, None]
        out[rows[:n_rest]] = running
        out[rows[n_rest:]] = running[-1]
    return out


def features(
    volts: np.ndarray,
    codes: np.ndarray,
    t: np.ndarray,
    spec: ModelInputs,
    transform: InputTransform | None = None,
) -> np.ndarray:
    """(n, channels) model inputs of volts (n, channels) whose rows belong to trials `codes` at
    times `t` (s), any row order; with a unit's calibration `transform`, as the models read that unit."""
    volts = np.asarray(volts, dtype=np.float64)
    rest = None
    if _relative(spec):
        rest = rest_reading(volts, np.asarray(codes), np.asarray(t, dtype=np.float64), spec.rest_s)
    return features_at(volts, rest, spec, transform)


def features_at(
    volts: np.ndarray, rest: np.ndarray | None, spec: ModelInputs, transform: InputTransform | None = None
) -> np.ndarray:
    """The model inputs of volts (n, channels) given the rest reading in effect at each row (same
    shape; not read by the absolute kinds): what the deployed graph computes."""
    x = _inputs_of(np.asarray(volts, dtype=np.float64), spec, transform)
    if _relative(spec):
        x = x - _inputs_of(np.asarray(rest, dtype=np.float64), spec, transform)
    return x if transform is None else transform.on_inputs(x)


def _inputs_of(volts: np.ndarray, spec: ModelInputs, transform: InputTransform | None) -> np.ndarray:
    """The absolute inputs of `volts` (a conductance-domain calibration applied first)."""
    return _absolute(volts if transform is None else transform.on_volts(volts), spec)


class RestReading:
    """The rest reading one sample at a time, for a live client: `push(t, volts)` -> the rest reading
    in effect for that sample (volts); `reset()` at the start of each insertion. The same numbers as
    `rest_reading` on the whole trial."""

    __slots__ = ("_frozen", "_n", "_rest_s", "_sum", "_t0")

    def __init__(self, rest_s: float, n_channels: int) -> None:
        self._rest_s = rest_s
        self._sum = np.zeros(n_channels)
        self.reset()

    def reset(self) -> None:
        self._sum[:] = 0.0
        self._n = 0
        self._t0: float | None = None
        self._frozen = False

    def push(self, t: float, volts: np.ndarray) -> np.ndarray:
        if self._t0 is None:
            self._t0 = t
        if not self._frozen and t - self._t0 < self._rest_s - 1e-9:
            self._sum += volts
            self._n += 1
        else:
            self._frozen = True
        return self._sum / self._n


DOMAINS = ("conductance", "inputs")  # where a unit's calibration acts (InputTransform.domain)
MIN_CONDUCTANCE_US = 1e-3  # floor of a calibrated conductance: a map must not open a loaded FSR


@dataclass(frozen=True)
class InputTransform:
    """A unit's affine map, fitted by its calibration so that the shared models read the unit as
    they read the training units. Identity by default. Where it acts (`domain`):

    - "conductance" (the unit declares its circuit): on each FSR's conductance, g' = g A^T + b in µS,
      the part-to-part quantity, before the model's inputs are computed from the volts of g' (through
      the unit's own circuit `front_end`), whatever inputs the model reads;
    - "inputs" (no circuit declared): on the model's inputs, x' = x A^T + b.
    """

    matrix: tuple[tuple[float, ...], ...]
    offset: tuple[float, ...]
    domain: str = "inputs"
    front_end: Divider | Transimpedance | None = None

    def __post_init__(self) -> None:
        if self.domain not in DOMAINS:
            raise ValueError(f"a unit's transform acts on {' or '.join(DOMAINS)}, not {self.domain!r}")
        if self.domain == "conductance" and self.front_end is None:
            raise ValueError("a transform on the FSRs' conductance needs the unit's circuit (front_end)")

    @classmethod
    def identity(cls, n: int) -> InputTransform:
        return cls(tuple(tuple(float(i == j) for j in range(n)) for i in range(n)), (0.0,) * n)

    @classmethod
    def from_dict(
        cls, d: Mapping[str, Any], front_end: Divider | Transimpedance | None = None
    ) -> InputTransform:
        """A stored transform (`to_dict`); a conductance-domain one reads through `front_end`, the
        circuit its unit declares."""
        a = np.asarray(d["matrix"], dtype=np.float64)
        b = np.asarray(d["offset"], dtype=np.float64)
        if (
            a.ndim != 2
            or a.shape[0] != a.shape[1]
            or b.shape != (a.shape[0],)
            or not (np.isfinite(a).all() and np.isfinite(b).all())
        ):
            raise ValueError(
                f"an input transform is a finite square matrix and offset, got {a.shape}, {b.shape}"
            )
        domain = str(d.get("domain", "inputs"))
        return cls(
            tuple(map(tuple, a.tolist())),
            tuple(b.tolist()),
            domain,
            front_end if domain == "conductance" else None,
        )

    def to_dict(self) -> dict[str, Any]:
        return {"matrix": [list(r) for r in self.matrix], "offset": list(self.offset), "domain": self.domain}

    @property
    def n(self) -> int:
        return len(self.offset)

    def _map(self, x: np.ndarray) -> np.ndarray:
        a = np.asarray(self.matrix, dtype=np.float64)
        return np.asarray(x, dtype=np.float64) @ a.T + np.asarray(self.offset, dtype=np.float64)

    def on_volts(self, volts: np.ndarray) -> np.ndarray:
        """The volts the unit would read with the calibrated conductance (a conductance-domain map;
        else the volts themselves): what the model's inputs are computed from."""
        if self.domain != "conductance":
            return np.asarray(volts, dtype=np.float64)
        fe = self.front_end
        g = self._map(conductance_us(volts, fe))  # type: ignore[arg-type]
        return volts_of_conductance(np.maximum(g, MIN_CONDUCTANCE_US), fe)  # type: ignore[arg-type]

    def on_inputs(self, x: np.ndarray) -> np.ndarray:
        """The model's inputs after an inputs-domain map (else unchanged)."""
        return self._map(x) if self.domain == "inputs" else np.asarray(x, dtype=np.float64)


# A unit as the deployed graph's `unit_circuit` input (pipeline.modelling.front, docs/deploy.md):
# [circuit, a, b, series_kohm, offset_v, calibrated on conductance]. circuit 0: none declared (the
# model reads the unit through its own circuit), 1: a divider with the FSR at the supply, 2: at ground,
# 3: a transimpedance stage; a, b: supply_v and fixed_kohm of a divider, drive_v and feedback_kohm of
# a transimpedance stage.
SUPPLY_DIVIDER, GROUND_DIVIDER, TRANSIMPEDANCE = 1.0, 2.0, 3.0
CIRCUIT_CODES = {
    ("divider", "supply"): SUPPLY_DIVIDER,
    ("divider", "ground"): GROUND_DIVIDER,
    ("transimpedance", None): TRANSIMPEDANCE,
}
ON_CONDUCTANCE = 5  # the place in `unit_circuit` of the flag "calibrated on conductance"


def encode_circuit(fe: Divider | Transimpedance | None, on_conductance: bool = False) -> np.ndarray:
    """A circuit (None: none declared) as the graph's six numbers."""
    if fe is None:
        return np.array([0.0, 0.0, 0.0, 0.0, 0.0, float(on_conductance)])
    if isinstance(fe, Divider):
        head = [CIRCUIT_CODES["divider", fe.fsr_at], fe.supply_v, fe.fixed_kohm, fe.series_kohm, 0.0]
    else:
        code = CIRCUIT_CODES["transimpedance", None]
        head = [code, fe.drive_v, fe.feedback_kohm, fe.series_kohm, fe.offset_v]
    return np.array([*head, float(on_conductance)], dtype=np.float64)


def unit_inputs(
    transform: InputTransform | None, front_end: Divider | Transimpedance | None, n_channels: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(unit_matrix, unit_offset, unit_circuit): how the deployed graph reads a unit, from its
    calibration `transform` (None: uncalibrated) and the circuit it declares (`front_end`, None: the
    model's own). The identity and no circuit read a unit as the training units were read."""
    t = InputTransform.identity(n_channels) if transform is None else transform
    on_conductance = t.domain == "conductance"
    fe = t.front_end if on_conductance else front_end
    return (
        np.asarray(t.matrix, dtype=np.float64),
        np.asarray(t.offset, dtype=np.float64),
        encode_circuit(fe, on_conductance),
    )
