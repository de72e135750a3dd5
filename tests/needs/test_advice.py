"""The advice: sentences computed from the curves, naming the numbers found and what to record next."""

from __future__ import annotations

from typing import Any

from pipeline.needs.advice import (
    cue_sentence,
    flattens,
    force_label,
    force_sentence,
    have_text,
    left_out_sentence,
    new_unit_sentence,
    reached,
    sentences,
)
from pipeline.needs.document import Curves, stored_curves
from tests.needs.docs import cues, needs_doc, step


def test_the_cues_reaching_the_target_name_where_and_what_the_lab_has() -> None:
    # given: balanced accuracy rising past 95 % at 12 insertions per angle
    points = [(3, 0.71), (6, 0.88), (12, 0.951), (27, 0.97)]
    # when
    text = cue_sentence(points, "27", 95, 3)
    # then
    assert text == (
        "The cues reach 95 % (balanced accuracy within 3 s, on the training units' held-out trials) at about "
        "12 insertions per angle (95.1 % there, 97.0 % with 27); you have 27."
    )


def test_the_cues_not_reaching_the_target_say_how_far_they_rose_and_to_record_more() -> None:
    # given: the example, 71 to 83 % from 4 to 9 insertions per angle
    text = cue_sentence([(4, 0.71), (9, 0.83)], "9", 95, 3)
    # then
    assert text is not None
    assert "do not reach 95 %" in text and "with the 9 you have" in text
    assert text.endswith(
        "from 4 to 9 insertions per angle they rose from 71.0 to 83.0 %: record more insertions per angle."
    )
    # and a curve that did not rise does not ask for more of the same
    flat = cue_sentence([(4, 0.83), (9, 0.80)], "9", 95, 3)
    assert flat is not None and flat.endswith(
        "fell from 83.0 to 80.0 %: more insertions per angle did not lift them here."
    )


def test_a_curve_that_dips_below_the_target_again_has_not_reached_it() -> None:
    # given / when / then: reached means reached and kept
    assert reached([(3, 0.96), (6, 0.93), (12, 0.97)], 0.95) == 2
    assert reached([(3, 0.96), (6, 0.97)], 0.95) == 0
    assert reached([(3, 0.96), (6, 0.90)], 0.95) is None


def test_the_force_curve_flattens_where_more_data_gains_less_than_5_percent() -> None:
    # given: 9.0 -> 7.5 (-17 %) -> 7.3 (-3 %) -> 7.2
    points = [(3, 9.0), (6, 7.5), (12, 7.3), (23, 7.2)]
    # when / then: it flattens at 6, and the sentence names the numbers
    assert flattens(points) == 1
    assert force_sentence("LS", points, "23") == (
        "The force error of LS flattens at about 6 insertions per angle: 7.50 % mean NRMSE there, 7.20 % "
        "with 23 (more insertions lower it by less than 5 %); you have 23."
    )


def test_a_force_curve_still_falling_at_the_end_asks_for_more() -> None:
    # given: each doubling still lowers the error by 10 % or more
    points = [(3, 9.0), (6, 8.0), (12, 7.0)]
    # when
    text = force_sentence("LS", points, "12")
    # then
    assert flattens(points) is None
    assert text == (
        "The force error of LS is still falling at 12 insertions per angle: from 6 to 12 it went from "
        "8.00 to 7.00 % mean NRMSE (12 % lower): record more insertions per angle for a lower force error."
    )


def test_the_left_out_curve_says_how_many_calibration_insertions_a_new_unit_needs() -> None:
    # given: the units left out reach 95 % at k = 2; the new unit's batch has 1 per angle
    text = left_out_sentence([(1, 0.888), (2, 0.951), (3, 0.96)], 3, 95, 3, {"est-101": 1})
    # then
    assert text == (
        "Calibration: a training unit read as a new one (each left out in turn, mean of 3 units) reaches "
        "95 % (balanced within 3 s) at 2 calibration insertions per angle (1: 88.8 %, 2: 95.1 %, 3: 96.0 %); "
        "est-101 has 1: record 2 per angle for a new unit's calibration batch."
    )
    # and a curve short of the target with the largest k asks for more calibration insertions
    short = left_out_sentence([(1, 0.60), (2, 0.70)], 2, 95, 3, {})
    assert short is not None and short.endswith(
        "(1: 60.0 %, 2: 70.0 %): record more calibration insertions per angle."
    )


def test_a_new_unit_s_own_batch_is_reported_with_what_it_could_not_show() -> None:
    # given / when
    text = new_unit_sentence("est-101", [(1, 0.893)], 1, (1, 2, 3))
    # then
    assert text == (
        "est-101's own calibration batch (1 per angle at the fewest) gives 89.3 % with 1 per angle on its "
        "held-out trials; 2, 3 per angle need a larger calibration batch."
    )


def test_what_the_lab_has_is_one_number_or_a_range() -> None:
    assert have_text({"0": 23, "15": 23}) == "23"
    assert have_text({"0": 23, "15": 27}) == "23 to 27 (by angle)"


WHY = "evidence stage 0: the trials fitted hold one per unit and angle"


def doc(loo: dict[str, Any] | None, units: list[str]) -> Curves:
    """A needs document's curves: three ladder steps (the first not scored), one new unit."""
    whole = needs_doc()
    whole["training"].update(
        have_per_angle={"0": 12},
        units=units,
        force_models=[{"name": "ls", "about": "LS"}],
        steps=[
            step(3, {"unavailable": f"no angle estimator could be fitted ({WHY})"}, {}),
            step(6, cues(0.8, 0.8), {"ls": 8.0}),
            step(12, cues(0.9, 0.8), {"ls": 7.9}),
        ],
    )
    whole["calibration"].update(
        new_units={"N": {"calibration_insertions": {"0": 1}, "steps": [{"k": 1, **cues(0.9, 0.8)}]}},
        leave_one_unit_out=loo,
    )
    del whole["advice"]
    return stored_curves(whole)


def test_the_advice_of_a_document_covers_cues_force_and_calibration_in_order() -> None:
    # given: a document with a leave-one-unit-out curve
    seen = cues(0, 0)["seen"]
    loo = {
        "units": {},
        "mean": [
            {"k": 1, "units": 2, "balanced_within_s": 0.7, "seen": seen},
            {"k": 2, "units": 2, "balanced_within_s": 0.8, "seen": seen},
        ],
    }
    # when
    found = sentences(doc(loo, ["A", "B"]))
    # then: the cues, the step that could not be scored and why, LS, the left-out curve, the new unit
    assert [s.split(" ")[:3] for s in found] == [
        ["The", "cues", "do"],
        ["With", "3", "insertions"],
        ["The", "force", "error"],
        ["Calibration:", "a", "training"],
        ["N's", "own", "calibration"],
    ]
    assert "from 6 to 12 insertions per angle they rose from 80.0 to 90.0 %" in found[0]
    assert found[1] == (
        "With 3 insertions per angle the cues could not be scored: no angle estimator could be fitted "
        f"({WHY})."
    )


def test_with_one_training_unit_the_advice_says_why_there_is_no_left_out_curve() -> None:
    # given / when
    found = sentences(doc(None, ["A"]))
    # then: said in one sentence, with what the new unit's own batch shows
    assert found[-1] == (
        "Leave-one-unit-out is not possible with one training unit (A): N's own calibration batch "
        "(1 per angle at the fewest) gives 90.0 % with 1 per angle on its held-out trials; 2 per angle need "
        "a larger calibration batch."
    )


def test_the_force_curves_are_named_after_their_kinds() -> None:
    # given: the curves of LS itself and of the FNN's stand-in / when / then: the kind's label, and the
    # stand-in named with the kinds it is not (every kind not fitted as it is)
    names = ["ls", "fnn_stand_in"]
    assert force_label("ls", names) == "LS"
    assert force_label("fnn_stand_in", names) == (
        "the networks' stand-in (a ridge regression, not the trained FNN or LSTM)"
    )
