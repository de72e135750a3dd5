"""A calibrated unit read through its map on the conductance (`UnitMap`, `cue_reading`): what the
cues read of it, and when they read it so (docs/units.md, "A new unit read through a map")."""

from __future__ import annotations

import numpy as np
import pandas as pd

from needlecue_runtime.cues.evidence import Evidence, UnitMap
from needlecue_runtime.cues.tracker import CueTracker
from needlecue_runtime.cues.units import cue_reading, departing_levels, unit_evidence
from needlecue_runtime.frontend import Divider, conductance_us, volts_of_conductance
from pipeline.config import CuesParams
from pipeline.cues.packs import build_cue_pack
from pipeline.cues.unit_evidence import trial_features
from tests.cues.synthetic import CHANNELS, NOMINAL, make_split, run_tracker, whole_pack

DIVIDER = Divider(circuit="divider", supply_v=5.0, fixed_kohm=10.0, series_kohm=1.62)
MIX = UnitMap(np.array([[1.1, 0.2, 0.0], [0.0, 0.9, 0.1], [0.05, 0.0, 1.0]]), np.zeros(3))


def _mapped_volts(frame: pd.DataFrame, m: UnitMap) -> pd.DataFrame:
    """The frame as a unit whose conductance is already the mapped one would record it."""
    out = frame.copy()
    g = conductance_us(frame[list(CHANNELS)].to_numpy(np.float64), DIVIDER)
    out[list(CHANNELS)] = volts_of_conductance(m.apply(g), DIVIDER)
    return out


def test_a_unit_read_through_its_map_is_read_as_its_mapped_conductance() -> None:
    # given: insertions of a unit with a declared divider, and a map mixing its channels
    p = CuesParams(evidence_levels=(0.05, 0.1, 0.2))
    frames = {30.0: make_split(30, ["b1"], 2, seed=4).assign(unit_id="u")}
    circuits = {"u": DIVIDER}
    # when: gathering its evidence through the map, and from volts recorded as the mapped conductance
    through = trial_features(frames, CHANNELS, p, circuits, p.evidence_levels, {"u": MIX})[0]
    recorded = trial_features(
        {30.0: _mapped_volts(frames[30.0], MIX)}, CHANNELS, p, circuits, p.evidence_levels
    )[0]
    # then: the same features, stage for stage (to the volts' round trip), and not those read as it is
    plain = trial_features(frames, CHANNELS, p, circuits, p.evidence_levels)[0]
    assert [t.stage for t in through] == [t.stage for t in recorded]
    for a, b, c in zip(through, recorded, plain, strict=True):
        np.testing.assert_allclose(a.features, b.features, atol=1e-5)
        assert not np.allclose(a.features, c.features, atol=1e-3)


def test_a_map_never_opens_a_loaded_fsr() -> None:
    # given: a map that would drive a conductance negative
    m = UnitMap(np.array([[1.0, -2.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]), np.zeros(3))
    ev = Evidence(3, (0.1,), 0.02, 2, 0.3, DIVIDER, m)
    # when / then: the evidence reads the calibration's floor, and can take its log
    g = ev.signal([1.0, 2.0, 2.5])
    assert g[0] == 1e-3 and np.isfinite(np.log(g)).all()


def _stage(width: int) -> dict:
    """An evidence stage of six classes a step of 1 apart in every (whitened) feature."""
    return {"means": [[float(c)] * width for c in range(6)], "precision": np.eye(width).tolist()}


PACK = whole_pack({"levels": [0.1], "stages": [_stage(2), _stage(4)], "classes_deg": [0, 15, 30, 45, 60, 75]})


def _evidence(off: float, rest_off: float = 0.0) -> dict:
    """One insertion per angle fitting a shift of the layout, its 0° and 75° cells `off` at stage 1
    (and `rest_off` at the rest reading)."""
    out = {}
    for c in range(6):
        rest = [c + 0.3 + (rest_off if c in (0, 5) else 0.0)] * 2
        loading = [c + 0.3 + (off if c in (0, 5) else 0.0)] * 4
        out[f"{15 * c:g}"] = {"n": [1, 1], "means": [rest, loading]}
    return out


def _cues(raw: dict, mapped: dict | None) -> dict:
    out = {"levels": [0.1], "evidence": raw}
    if mapped is not None:
        out["mapped"] = {
            "kind": "lstm",
            "matrix": MIX.matrix.tolist(),
            "offset": [0.0] * 3,
            "evidence": mapped,
        }
    return out


def test_a_unit_departing_as_it_is_but_not_through_its_map_is_read_through_it() -> None:
    # given: a calibration whose insertions depart at stage 1 as they are, and fit through the map
    departing, fitting = _evidence(3.0), _evidence(0.0)
    # when
    evidence, unit_map = cue_reading(PACK, _cues(departing, fitting))
    # then: the mapped evidence, with the map
    assert evidence == fitting
    assert unit_map is not None and np.array_equal(unit_map.matrix, MIX.matrix)


def test_a_unit_that_departs_nowhere_or_still_through_its_map_is_read_as_it_is() -> None:
    # given: insertions that fit as they are; or that still depart through the map; or no map
    fitting, departing = _evidence(0.0), _evidence(3.0)
    # when / then: as it is, without a map
    assert cue_reading(PACK, _cues(fitting, departing)) == (fitting, None)
    assert cue_reading(PACK, _cues(departing, _evidence(-3.0))) == (departing, None)
    # and: a map that leaves fewer departing stages, but some, is not taken
    everywhere = _evidence(3.0, rest_off=3.0)
    assert departing_levels(PACK, everywhere) == [0, 1] and departing_levels(PACK, departing) == [1]
    assert cue_reading(PACK, _cues(everywhere, departing)) == (everywhere, None)
    assert cue_reading(PACK, _cues(departing, None)) == (departing, None)
    # and: evidence at other levels than the estimator's is no reading at all
    assert cue_reading(PACK, {**_cues(departing, fitting), "levels": [0.2]}) == (None, None)


def _posteriors(tracker: CueTracker, frame: pd.DataFrame) -> list:
    """Per frame: the cue shown and P(angle) (None before the rest reading)."""
    out = []
    for state in run_tracker(tracker, frame):
        p = tracker.posterior()
        out.append((state.cue, None if p is None else np.round(p, 6).tolist()))
    return out


def test_a_tracker_reading_through_a_map_reads_as_on_the_mapped_volts(train_by_angle, params) -> None:
    # given: a pack of a unit with a declared divider, and that unit's insertion at 45°
    pack = build_cue_pack(train_by_angle, 30, params, circuits={NOMINAL: DIVIDER})
    trial = make_split(45, ["x"], 1, seed=21)
    known = unit_evidence(pack, NOMINAL)
    # when: one tracker reads it through a map, another reads volts recorded as the mapped conductance
    through = CueTracker(pack, 30, unit_evidence=known, front_end=DIVIDER, unit_map=MIX)
    recorded = CueTracker(pack, 30, unit_evidence=known, front_end=DIVIDER)
    # then: the same cue and posterior, frame by frame; not those of the unit read as it is
    mapped = _posteriors(through, trial)
    assert mapped == _posteriors(recorded, _mapped_volts(trial, MIX))
    plain = _posteriors(CueTracker(pack, 30, unit_evidence=known, front_end=DIVIDER), trial)
    assert mapped != plain
    # and: told to read the unit as it is again, it does so from its next insertion
    through.use_unit_map(None)
    assert _posteriors(through, trial) == plain
