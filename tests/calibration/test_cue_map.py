"""A unit's calibration document carries its cue evidence as it is and through its best map."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from needlecue_runtime.cues.evidence import UnitMap
from needlecue_runtime.frontend import Divider
from pipeline.calibration.unit import cue_evidence, cue_map_kind
from pipeline.config import CuesParams
from pipeline.cues.unit_evidence import evidence_of, trial_features
from tests.cues.synthetic import CHANNELS, make_split

DIVIDER = Divider(circuit="divider", supply_v=5.0, fixed_kohm=10.0, series_kohm=1.62)
EYE = np.eye(3).tolist()
MIX = [[1.1, 0.2, 0.0], [0.0, 0.9, 0.1], [0.05, 0.0, 1.0]]


def _transform(loss: float, held_out: float | None = None, **extra) -> dict:
    out = {"matrix": MIX, "offset": [0.0] * 3, "domain": "conductance", "loss_after": loss, **extra}
    return out if held_out is None else {**out, "held_out_loss_after": held_out}


def test_the_cue_map_is_the_kept_conductance_map_that_fits_the_unit_best() -> None:
    # given: three kinds' maps, the best on the angles left out being the LSTM's
    transforms = {
        "ls": _transform(0.13, 0.14),
        "fnn": _transform(0.02, 0.04),
        "lstm": _transform(0.01, 0.009),
    }
    # when / then: the LSTM's; with it kept as the identity, the FNN's
    assert cue_map_kind(transforms) == "lstm"
    transforms["lstm"]["identity_kept"] = "leave-one-angle-out, ..."
    assert cue_map_kind(transforms) == "fnn"
    # and: a map on the model's inputs (no circuit declared) is no map of the conductance
    assert cue_map_kind({"ls": {**_transform(0.1), "domain": "inputs"}}) is None


def test_the_document_holds_the_evidence_as_it_is_and_through_the_map_as_stored() -> None:
    # given: a unit's calibration insertions at two angles, its circuit declared, and its LSTM map kept
    p = CuesParams(evidence_levels=(0.05, 0.1, 0.2))
    rows = {str(a): make_split(a, ["cal"], 1, seed=9).assign(unit_id="u") for a in (30, 45)}
    models = {"lstm": {"30": SimpleNamespace(channels=CHANNELS)}}
    transforms = {"lstm": _transform(0.01, 0.02, matrix=(np.asarray(MIX) + 1e-9).tolist())}
    # when
    cues = cue_evidence("u", rows, models, p, DIVIDER, p.evidence_levels, transforms)
    # then: as it is, the evidence read without a map
    frames = {float(a): f for a, f in rows.items()}
    plain = trial_features(frames, CHANNELS, p, {"u": DIVIDER}, p.evidence_levels)[0]
    assert cues["evidence"] == evidence_of(plain, 3)["u"]
    # and: through the map as the document stores it (6 decimals), naming whose map it is
    mapped = cues["mapped"]
    assert (mapped["kind"], mapped["matrix"]) == ("lstm", MIX)
    through = trial_features(
        frames, CHANNELS, p, {"u": DIVIDER}, p.evidence_levels, {"u": UnitMap.of(mapped)}
    )
    assert mapped["evidence"] == evidence_of(through[0], 3)["u"] != cues["evidence"]
    # and: without a circuit (a map on the model's inputs) there is nothing to read through
    assert "mapped" not in cue_evidence(
        "u", rows, models, p, None, p.evidence_levels, {"lstm": {**transforms["lstm"], "domain": "inputs"}}
    )
