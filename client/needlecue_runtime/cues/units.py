"""Which estimator unit the angle estimator reads, and how it knows it: by its training trials in the
pack, by its calibration insertions, or not at all (`reading_of`); the evidence it reads it by
(`unit_evidence`, `cue_reading`), and each evidence stage's reading of it (`unit_readings`: its class
means and how sure they are, `needlecue_runtime.cues.reading`). Numpy and pydantic only: the
simulator's client imports this module.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import replace
from typing import Any

import numpy as np

from needlecue_runtime.cues.evidence import UnitMap
from needlecue_runtime.cues.pack import CuePack, EstimatorStage, as_pack
from needlecue_runtime.cues.reading import Cell, UnitReading, read_unit

UnitEvidence = Mapping[str, Mapping[str, Any]]  # {angle: {"n": [per stage], "means": [per stage]}}

Pack = CuePack | Mapping[str, Any]  # a typed pack, or one as a dict (a model's metadata, `build_cue_pack`)


def _units(pack: Pack) -> dict[str, Any]:
    est = as_pack(pack).angle_estimator
    return {} if est is None else est.units


def reading_of(pack: Pack, unit_id: str | None, calibration: UnitEvidence | None) -> str:
    """How the angle estimator knows a unit: by its calibration insertions ("calibrated-<k>", k the
    fewest insertions it has at an angle), by its training trials in the pack ("training"), or not at
    all ("uncalibrated"). Each has its own cross-validated temperature and confidence in the pack
    where training allowed (`pipeline.cues.estimator`); `CueTracker.set_unit` picks the nearest."""
    if calibration:
        k = min((int(e["n"][0]) for e in calibration.values() if e.get("n")), default=1)
        return f"calibrated-{max(k, 1)}"
    return "training" if unit_id is not None and unit_id in _units(pack) else "uncalibrated"


def validated_reading(reading: str, validated: Sequence[str]) -> str | None:
    """The reading whose cross-validated numbers apply to `reading`: itself if validated; for a unit
    calibrated from k insertions per angle, the deepest validated calibration of at most k
    insertions (else the shallowest, else "training": one training unit, nothing could be left
    out); for an uncalibrated unit, None unless it was validated (too few training units to leave
    one out and still bound it: it gets no angle cue)."""
    if reading in validated:
        return reading
    if reading == "uncalibrated":
        return None
    if reading.startswith("calibrated-"):
        k = int(reading.rsplit("-", 1)[1])
        depths = sorted(int(r.rsplit("-", 1)[1]) for r in validated if r.startswith("calibrated-"))
        if depths:
            return f"calibrated-{max([d for d in depths if d <= k] or [depths[0]])}"
    return "training"


def unit_evidence(
    pack: Pack, unit_id: str | None, calibration: UnitEvidence | None = None
) -> UnitEvidence | None:
    """What the angle estimator knows of an estimator unit (`pipeline.cues.unit_evidence`): its calibration's
    evidence when given, else a training unit's from the pack, else None (an uncalibrated unit: the
    estimator's average unit)."""
    if calibration:
        return calibration
    cells = _units(pack).get(unit_id) if unit_id is not None else None
    # as plain mappings, the shape a calibration's evidence has
    return None if cells is None else {a: c.model_dump() for a, c in cells.items()}


def calibration_evidence(pack: Pack, cues: Mapping[str, Any] | None) -> UnitEvidence | None:
    """The evidence in a unit calibration's `cues` section ({"levels", "evidence"}) if it was gathered
    at the loading levels of this pack's angle estimator, else None (features at other levels are
    not the estimator's: the unit is then read as the average one)."""
    if not cues or not cues.get("evidence"):
        return None
    est = as_pack(pack).angle_estimator
    levels = np.asarray([] if est is None else est.levels, dtype=np.float64)
    mine = np.asarray(cues.get("levels") or [], dtype=np.float64)[: len(levels)]
    # as stored: the document keeps 6 decimals (an absolute 5e-7), the pack 6 significant digits
    same = len(mine) == len(levels) and np.allclose(mine, levels, rtol=1e-5, atol=1e-6)
    return cues["evidence"] if same else None


def cue_reading(pack: Pack, cues: Mapping[str, Any] | None) -> tuple[UnitEvidence | None, UnitMap | None]:
    """How the angle estimator reads a calibrated unit, from its calibration's `cues` section: (its
    evidence, the map its conductance is read through, or None: as it is).

    As it is, unless its calibration insertions depart from the training units' layout at some
    evidence stage (`departing_levels`: no angle cue there) and, read through the unit's map on its
    conductance (`cues.mapped`: the map of the model kind that fits it best, `pipeline.calibration.
    unit`), they depart nowhere. A unit that departs nowhere is read as it is: through the force
    models' map it would be read in a layout cross-validation never saw, and on the family's units
    that cost more wrong cues than the 2 % a trainee may see. A map that leaves the unit departing
    somewhere is not taken either: measured once, it added wrong cues (docs/units.md, "A new unit
    read through a map")."""
    pack = as_pack(pack)
    evidence = calibration_evidence(pack, cues)
    if not evidence or not cues or not cues.get("mapped"):
        return evidence, None
    mapped = cues["mapped"]
    through = mapped.get("evidence")  # gathered at the same levels, which `evidence` has matched
    if through and departing_levels(pack, evidence) and not departing_levels(pack, through):
        return through, UnitMap.of(mapped)
    return evidence, None


def _cells(classes: Sequence[float], evidence: UnitEvidence | None, j: int) -> list[Cell]:
    """The unit's cells at evidence stage j: per class, its trials that reached the stage."""
    cells = []
    for c, a in enumerate(classes):
        e = (evidence or {}).get(f"{float(a):g}")
        if e and len(e["n"]) > j and e["n"][j] > 0:
            cells.append((c, float(e["n"][j]), np.asarray(e["means"][j], dtype=np.float64)))
    return cells


def unit_readings(
    stages: Sequence[EstimatorStage],
    classes: Sequence[float],
    evidence: UnitEvidence | None,
    trained: bool = False,
) -> list[UnitReading]:
    """How each evidence stage reads the unit of `evidence` (None: an uncalibrated unit): its class
    means and their uncertainty (`needlecue_runtime.cues.reading.read_unit`), with the stage's
    `template_weight` and `offset_spread`. A unit training did not see (not `trained`) is also
    tested, with the stage's precision, for departing from the training units' layout, and a
    departure is kept at later stages that fewer of the unit's classes reach: a stage's features hold
    every earlier stage's, and a departure seen with an angle's cell cannot be undone by a stage
    without it (four cells of the middle angles can fit a shift where six did not). A later stage
    with as many cells judges anew: it has more features to judge by."""
    out: list[UnitReading] = []
    widest = 0  # the most cells an earlier stage departed with
    for j, stage in enumerate(stages):
        cells = _cells(classes, evidence, j)
        r = read_unit(
            np.asarray(stage.means, dtype=np.float64),
            cells,
            stage.template_weight,
            stage.offset_spread,
            None if trained else np.asarray(stage.precision, dtype=np.float64),
        )
        if not r.departs and widest > len(cells):
            r = replace(r, departs=True)
        if r.departs:
            widest = max(widest, len(cells))
        out.append(r)
    return out


def departing_levels(pack: Pack, evidence: UnitEvidence) -> list[int]:
    """The evidence stages (0: the rest reading, j: the j-th loading level) at which a calibrated
    unit's insertions sit unlike any shift of the training units' layout (`UnitReading.departs`,
    carried forward by `unit_readings`): there it gets no angle cue ("outside what training
    covered")."""
    est = as_pack(pack).angle_estimator
    if est is None:
        return []
    return [j for j, r in enumerate(unit_readings(est.stages, est.classes_deg, evidence)) if r.departs]
