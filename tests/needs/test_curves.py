"""The needs curves of a small lab: the ladder spread over the units, cue figures that do not get worse
with more training insertions, the calibration curves of a new unit and of each unit left out, and
what cannot be computed said."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from pipeline.config import CuesParams, NeedsParams
from pipeline.modelling.kinds.fnn import FNNParams
from pipeline.modelling.kinds.ls import LSParams
from pipeline.needs.curves import needs_curves
from pipeline.needs.force import ForceModel, force_models
from tests.needs.lab import ANGLES, NEW_UNIT, TRAINING_UNITS, lab_data, lab_frames, write_choices

CUES = CuesParams(kinds=("ls",), evidence_levels=(0.05, 0.1, 0.2))


def models(tmp_path: Path) -> dict[str, ForceModel]:
    """LS and the networks' stand-in on rest volts, as the stage builds them."""
    found, _ = force_models([("ls", LSParams()), ("fnn", FNNParams())], write_choices(tmp_path), {}, [])
    return found


@pytest.fixture(scope="module")
def needs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """The curves of the lab: 3 units x 2 batches x 2 insertions (12 per angle), the auto ladder."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("NEEDLECUE_WORKERS", "1")  # in-process: the stage test checks the worker processes
        return needs_curves(
            lab_data(lab_frames()),
            NeedsParams(),
            CUES,
            models(tmp_path_factory.mktemp("choices")),
            "ls",
            lambda _m: None,
        )


def test_the_ladder_steps_are_spread_over_the_units(needs: dict[str, Any]) -> None:
    # given: the lab has 12 training insertions per angle / then: the ladder 3, 6, 12, each step's
    # trials shared evenly by the three units
    training = needs["training"]
    assert training["ladder"] == [3, 6, 12]
    assert training["have_per_angle"] == {f"{a:g}": 12 for a in ANGLES}
    for step in training["steps"]:
        assert step["trials"] == step["per_angle"] * len(ANGLES)
        assert set(step["by_unit"].values()) == {step["per_angle"] * len(ANGLES) // 3}


def test_more_training_insertions_do_not_make_the_cues_worse(needs: dict[str, Any]) -> None:
    # given: the cue figures along the ladder
    steps = needs["training"]["steps"]
    # then: with one insertion per unit and angle (3 per angle) the estimator has no scatter to fit, and
    # says so; from 6 on, balanced accuracy and the frames with a cue never drop as insertions are added
    assert steps[0]["cues"]["unavailable"].startswith("no angle estimator could be fitted")
    assert "nothing shows how trials scatter" in steps[0]["cues"]["unavailable"]
    scored = [s["cues"] for s in steps[1:]]
    balanced = [c["balanced_within_s"] for c in scored]
    coverage = [c["seen"]["coverage_frames"] for c in scored]
    assert balanced == sorted(balanced) and balanced[-1] >= 0.95
    assert coverage == sorted(coverage)
    assert all(c["seen"]["wrong_final"] == 0 for c in scored)
    assert all(c["trials"] == 2 * len(TRAINING_UNITS) * len(ANGLES) for c in scored)


def test_the_force_curves_come_from_ls_and_the_networks_stand_in(needs: dict[str, Any]) -> None:
    # then: every step has both, named for what they are (not the trained networks)
    training = needs["training"]
    assert [m["name"] for m in training["force_models"]] == ["ls", "fnn_stand_in"]
    assert "not a trained FNN or LSTM" in training["force_models"][1]["about"]
    for step in training["steps"]:
        assert set(step["force"]) == {"ls", "fnn_stand_in"}


def test_the_calibration_curves_of_the_new_unit_and_of_each_unit_left_out(needs: dict[str, Any]) -> None:
    cal = needs["calibration"]
    # then: the new unit scored with 1 and 2 of its 2 calibration insertions per angle; 3 is said to need more
    new = cal["new_units"][NEW_UNIT]
    assert [s["k"] for s in new["steps"]] == [1, 2]
    assert all(s["trials"] == 2 * len(ANGLES) for s in new["steps"])
    assert {"what": f"{NEW_UNIT} with 3 calibration insertions per angle"} in [
        {"what": n["what"]} for n in needs["not_computed"]
    ]
    # and each training unit left out: k = 1, 2, 3 on the same trials (its 4th insertion per angle and
    # its held-out ones), their mean over the three units
    loo = cal["leave_one_unit_out"]
    assert sorted(loo["units"]) == list(TRAINING_UNITS)
    for entry in loo["units"].values():
        assert entry["test_trials"] == (1 + 2) * len(ANGLES)
        assert [s["k"] for s in entry["steps"]] == [1, 2, 3]
        assert {s["trials"] for s in entry["steps"]} == {entry["test_trials"]}
    mean = loo["mean"]
    assert [m["k"] for m in mean] == [1, 2, 3] and {m["units"] for m in mean} == {3}
    expected = np.mean([e["steps"][0]["balanced_within_s"] for e in loo["units"].values()])
    assert mean[0]["balanced_within_s"] == pytest.approx(expected)
    # and force against calibration insertions is said not to be recomputed
    assert cal["force"].startswith("not recomputed")


def test_with_one_training_unit_leave_one_unit_out_is_said_not_possible() -> None:
    # given: one training unit and the new unit's calibration batch
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("NEEDLECUE_WORKERS", "1")
        # when
        found = needs_curves(
            lab_data(lab_frames(units=("A",), per_batch=3)),
            NeedsParams(training_insertions=(6,), calibration_insertions=(1,)),
            CUES,
            {},
            "ls",
            lambda _m: None,
        )
    # then: no leave-one-unit-out curve, and why; the new unit's own batch still scored
    assert found["calibration"]["leave_one_unit_out"] is None
    assert {
        "what": "leave-one-unit-out calibration curve",
        "why": "one training unit (A): no other unit to fit the estimator on",
    } in found["not_computed"]
    assert found["calibration"]["new_units"][NEW_UNIT]["steps"][0]["balanced_within_s"] is not None
