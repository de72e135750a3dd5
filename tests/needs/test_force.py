"""Force against the training insertions per angle: per model kind given, the kind itself (LS) or the
networks' stand-in refitted per angle, scored on the training units' held-out trials; what cannot be
built or scored is said."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from pipeline.modelling.kinds.fnn import FNNParams
from pipeline.modelling.kinds.ls import LSParams
from pipeline.modelling.kinds.lstm import LSTMParams
from pipeline.needs.force import ForceModel, chosen_kind, force_curve, force_models
from pipeline.needs.subsample import spread_order, trials_in
from tests.needs.lab import ANGLES, NEW_UNIT, lab_frames, write_choices


def models(tmp_path: Path) -> dict[str, ForceModel]:
    """LS and the stand-in as the stage builds them: on the inputs the choose stage chose."""
    kinds = [("ls", LSParams()), ("fnn", FNNParams())]
    found, notes = force_models(kinds, write_choices(tmp_path / "choices"), {}, ["A"])
    assert notes == []
    return found


def test_force_is_scored_per_angle_for_each_model_and_a_failing_model_is_said(tmp_path: Path) -> None:
    # given: the lab's training and held-out trials of the training units, and a model that cannot read them
    frames = lab_frames(per_batch=1)
    train = frames["train"]
    same = {a: f[f["unit_id"] != NEW_UNIT].reset_index(drop=True) for a, f in frames["external"].items()}
    orders = {a: spread_order(trials_in(f), 0, str(a)) for a, f in train.items()}
    selections = [{a: o[:n] for a, o in orders.items()} for n in (3, 6)]

    def broken(_train: pd.DataFrame, _rows: pd.DataFrame) -> np.ndarray:
        raise ValueError("the broken model reads no such channel")

    given = {**models(tmp_path), "broken": ForceModel("a model that fails", broken)}
    # when
    steps, notes = force_curve(train, same, selections, given, lambda _m: None)
    # then: per step, LS and the stand-in at every angle, their mean finite; the broken one left out, and said
    for step in steps:
        assert set(step) == {"ls", "fnn_stand_in"}
        for figures in step.values():
            assert set(figures["by_angle"]) == {f"{a:g}" for a in ANGLES}
            assert np.isfinite(figures["mean_nrmse_pct"]) and figures["mean_nrmse_pct"] > 0
    assert notes == [{"what": "force of broken", "why": "the broken model reads no such channel"}]


def test_force_without_held_out_trials_of_a_training_unit_is_said(tmp_path: Path) -> None:
    # given: no external trial of a training unit / when / then: nothing scored, and why
    steps, notes = force_curve({}, {}, [{}], models(tmp_path), lambda _m: None)
    assert steps == [{}]
    assert notes[0]["why"] == "no external trial of a training unit"


def test_the_inputs_are_those_the_train_stage_gives(tmp_path: Path) -> None:
    # given: the choose stage's files choosing rest_volts, and params pinning conductance for the FNN
    choices = write_choices(tmp_path / "choices")
    pinned = FNNParams.model_validate({"inputs": {"kind": "conductance"}})
    # when / then: auto reads the choice, a pinned kind wins, a missing file is named
    assert chosen_kind("ls", LSParams(), choices) == "rest_volts"
    assert chosen_kind("fnn", pinned, choices) == "conductance"
    with pytest.raises(ValueError, match=r"nowhere/ls\.json: missing"):
        chosen_kind("ls", LSParams(), tmp_path / "nowhere")


def test_models_that_need_a_circuit_the_units_do_not_share_are_said(tmp_path: Path) -> None:
    # given: LS pinned to conductance, and training units that declare no circuit
    pinned = LSParams.model_validate({"inputs": {"kind": "conductance"}})
    choices = write_choices(tmp_path / "choices")
    # when
    found, notes = force_models([("ls", pinned), ("fnn", FNNParams())], choices, {"A": None}, ["A"])
    # then: the stand-in is built, LS is not, and why
    assert list(found) == ["fnn_stand_in"]
    assert notes[0]["what"] == "force of ls" and "needs the estimator's front end" in notes[0]["why"]


def test_the_force_curves_are_named_and_described_from_the_kinds_given(tmp_path: Path) -> None:
    # given: the kinds in another order, and the LSTM's stand-in (with its lags) among them
    kinds = [("fnn", FNNParams()), ("lstm", LSTMParams()), ("ls", LSParams())]
    # when
    found, notes = force_models(
        kinds, write_choices(tmp_path / "choices", models=("ls", "fnn", "lstm")), {}, ["A"]
    )
    # then: one curve per kind in the order given: a linear stand-in's kind fitted as it is, the others'
    # stand-ins, each described from its kind's label and stand-in
    assert notes == []
    assert list(found) == ["fnn_stand_in", "lstm_stand_in", "ls"]
    assert found["ls"].about == "LS (the paper's calibration matrix) on rest_volts"
    assert found["fnn_stand_in"].about == (
        "the networks' stand-in (ridge on the FNN's inputs rest_volts, their squares and pairwise products), "
        "not a trained FNN or LSTM"
    )
    assert "the LSTM's inputs rest_volts" in found["lstm_stand_in"].about
    assert ", lags [" in found["lstm_stand_in"].about
