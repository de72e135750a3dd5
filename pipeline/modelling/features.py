"""The model's inputs computed from the estimator's volts, and a unit's affine map on them.

Every estimator unit differs (docs/physics.md, "Estimator units"): each FSR's cast-in preload sets
its rest reading, its part-to-part gain scales its response, and the tripod's placement mixes the
lateral force differently. Raw volts carry all of that into the weights. The kinds here take out
what physics says is unit-specific and leaves the rest linear:

- `volts`: the divider's output as read (the paper's input);
- `rest_volts`: volts minus the trial's rest reading (removes most of the preload);
- `conductance`: the FSR conductance (µS) from inverting the divider, R = R_M (V+/v - 1),
  G = 1/(R - R_i) - 1/R_open; above actuation G grows in proportion to the load;
- `rest_conductance`: conductance minus the trial's rest conductance: the load added by the needle,
  times each FSR's gain. The preload drops out; gain and placement are left as a linear map per
  unit, which is what a unit's calibration (`InputTransform`) fits.

The rest reading is causal: the mean of a trial's samples in its first `rest_s` seconds (the
running mean until then), the same number in training, in batch prediction and in the live
client (`StreamFeatures`). Numpy only: the simulator's client imports this module.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, get_args

import numpy as np

from pipeline.config import DividerParams, InputParams

KINDS: tuple[str, ...] = get_args(InputParams.model_fields["kind"].annotation)
MIN_VOLTS = 1e-3  # an unloaded FSR reads a few mV; below this the divider cannot be inverted
MIN_R_KOHM = 0.1  # floor of R - R_i: near V+ the series term would make it negative


def spec_of(stored: Mapping[str, Any] | None) -> InputParams:
    """The inputs a checkpoint or deployable model records (`<model>.inputs` of params.yaml, checked
    the same way: an unknown setting or kind is a ValueError); None, a model from before inputs were
    recorded, reads raw volts."""
    return InputParams() if stored is None else InputParams.model_validate(stored)


def _relative(spec: InputParams) -> bool:
    """Whether the inputs are relative to the trial's rest reading."""
    return spec.kind.startswith("rest_")


def conductance_us(volts: np.ndarray, spec: DividerParams | InputParams) -> np.ndarray:
    """FSR conductance in µS from divider volts (elementwise), through `spec`'s divider."""
    v = np.clip(np.asarray(volts, dtype=np.float64), MIN_VOLTS, spec.v_plus - MIN_VOLTS)
    r = spec.r_m_kohm * (spec.v_plus / v - 1.0)
    g = 1.0 / np.maximum(r - spec.r_series_kohm, MIN_R_KOHM) - 1.0 / spec.r_open_kohm
    return g * 1e3  # 1/kOhm -> µS


def _absolute(volts: np.ndarray, spec: InputParams) -> np.ndarray:
    volts = np.asarray(volts, dtype=np.float64)
    return conductance_us(volts, spec) if spec.kind.endswith("conductance") else volts


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


def features(volts: np.ndarray, codes: np.ndarray, t: np.ndarray, spec: InputParams) -> np.ndarray:
    """(n, channels) model inputs of volts (n, channels) whose rows belong to trials `codes` at
    times `t` (s); any row order."""
    x = _absolute(volts, spec)
    if not _relative(spec):
        return x
    return x - rest_reading(x, np.asarray(codes), np.asarray(t, dtype=np.float64), spec.rest_s)


class StreamFeatures:
    """`features` one sample at a time, for the live client: `push(t, volts)` -> inputs; `reset()`
    at the start of each insertion. Gives the same numbers as `features` on the whole trial."""

    __slots__ = ("_frozen", "_n", "_spec", "_sum", "_t0")

    def __init__(self, spec: InputParams, n_channels: int) -> None:
        self._spec = spec
        self._sum = np.zeros(n_channels)
        self.reset()

    def reset(self) -> None:
        self._sum[:] = 0.0
        self._n = 0
        self._t0: float | None = None
        self._frozen = False

    @property
    def rest_ready(self) -> bool:
        """Whether the rest reading is complete (`rest_s` of samples seen)."""
        return self._frozen

    def push(self, t: float, volts: np.ndarray) -> np.ndarray:
        x = _absolute(volts, self._spec)
        if not _relative(self._spec):
            return x
        if self._t0 is None:
            self._t0 = t
        if not self._frozen and t - self._t0 < self._spec.rest_s - 1e-9:
            self._sum += x
            self._n += 1
        else:
            self._frozen = True
        return x - self._sum / self._n


@dataclass(frozen=True)
class InputTransform:
    """A unit's affine map on a model's inputs, x' = x A^T + b, fitted by its calibration so that the
    shared models read the unit as they read the training units. Identity by default."""

    matrix: tuple[tuple[float, ...], ...]
    offset: tuple[float, ...]

    @classmethod
    def identity(cls, n: int) -> InputTransform:
        return cls(tuple(tuple(float(i == j) for j in range(n)) for i in range(n)), (0.0,) * n)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> InputTransform:
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
        return cls(tuple(map(tuple, a.tolist())), tuple(b.tolist()))

    def to_dict(self) -> dict[str, Any]:
        return {"matrix": [list(r) for r in self.matrix], "offset": list(self.offset)}

    @property
    def n(self) -> int:
        return len(self.offset)

    def apply(self, x: np.ndarray) -> np.ndarray:
        a = np.asarray(self.matrix, dtype=np.float64)
        return np.asarray(x, dtype=np.float64) @ a.T + np.asarray(self.offset, dtype=np.float64)
