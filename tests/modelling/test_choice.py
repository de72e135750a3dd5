"""Inputs chosen by validation on the data at hand (`inputs.kind: auto`): the kind that carries the
force across units wins, conductance only through a declared circuit, and the choice is recorded."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pandas as pd
import pytest

from needlecue_runtime.frontend import Divider, Transimpedance, volts_of
from needlecue_runtime.vocab import AXES
from pipeline.config import InputParams
from pipeline.modelling.choice import Choice, candidates, choose_inputs, load_choice, pool, save_choice
from pipeline.modelling.fit import fit
from pipeline.modelling.kinds import kind_of
from pipeline.modelling.kinds.fnn import FNNParams
from pipeline.modelling.kinds.ls import LSParams
from pipeline.modelling.kinds.lstm import LSTMParams

CHANNELS = ["fsr1", "fsr2", "fsr3"]
DIVIDER = Divider(circuit="divider", supply_v=5.0, fixed_kohm=10.0)
LEAST_SQUARES = kind_of("ls").stand_in(LSParams(fit_intercept=False))  # each kind's own stand-in
NETWORK = kind_of("fnn").stand_in(FNNParams())
LSTM_15 = kind_of("lstm").stand_in(LSTMParams(window=15))
MIX = np.array([[0.8, -0.4, 0.1], [0.2, 0.5, -0.6], [0.4, 0.4, 0.4]])  # load on each FSR -> force


def _units(circuit, preloads: dict[str, float], seed: int = 0) -> pd.DataFrame:
    """Trials of several units: each FSR's conductance is its unit's preload plus the load, which
    sets the force linearly; the volts come through `circuit`."""
    rng = np.random.default_rng(seed)
    parts = []
    for unit, preload in preloads.items():
        for k in range(4):
            t = np.arange(120) / 30.0
            push = np.clip(np.sin(np.pi * t / 4.0), 0, None)[:, None] * rng.uniform(0.5, 1.5, 3)
            push[t < 0.6] = 0.0  # a rest reading before the load
            g_us = 1e3 * (preload + 0.02 * push)  # conductance in µS: the load adds in proportion
            volts = volts_of(1e3 / g_us, circuit)
            force = (push @ MIX.T) + rng.normal(0, 1e-3, (len(t), 3))
            parts.append(
                pd.DataFrame(
                    {
                        "batch_id": f"b-{unit}",
                        "trial_id": f"t{k}",
                        "unit_id": unit,
                        "t_s": t,
                        **dict(zip(CHANNELS, volts.T, strict=True)),
                        **dict(zip(AXES, force.T, strict=True)),
                    }
                )
            )
    return pd.concat(parts, ignore_index=True)


UNITS = {"u1": 0.004, "u2": 0.012, "u3": 0.020}  # three units, three cast-in preloads


def test_across_units_of_different_preload_a_rest_relative_conductance_wins():
    # given: three units of one declared circuit whose preloads differ
    rows = _units(DIVIDER, UNITS)
    # when: least squares' inputs are chosen by leave-one-unit-out
    choice = choose_inputs(LEAST_SQUARES, rows, rows.iloc[:0], CHANNELS, DIVIDER, rest_s=0.5)
    # then: the kind that is linear in the load and blind to the preload wins, by far
    assert choice.folds == "leave-one-unit-out (3 units)"
    assert choice.chosen == "rest_conductance"
    assert choice.scores["rest_conductance"] < 0.5 * min(choice.scores["volts"], choice.scores["conductance"])


def test_without_a_declared_circuit_no_conductance_is_a_candidate():
    rows = _units(DIVIDER, UNITS)
    assert candidates(None) == ["volts", "rest_volts"]
    choice = choose_inputs(NETWORK, rows, rows.iloc[:0], CHANNELS, None, rest_s=0.5)
    assert set(choice.scores) == {"volts", "rest_volts"} and choice.chosen == "rest_volts"


def test_a_model_that_must_serve_a_unit_of_another_circuit_reads_conductance():
    # given: units of one divider, and a held-out unit that declares an op-amp front end
    rows = _units(DIVIDER, UNITS)
    # when: the networks' inputs are chosen knowing of that unit
    choice = choose_inputs(NETWORK, rows, rows.iloc[:0], CHANNELS, DIVIDER, rest_s=0.5, other_designs=["u9"])
    # then: only the kinds that read the FSR itself were candidates, and the record says why
    assert candidates(DIVIDER, ["u9"]) == ["conductance", "rest_conductance"]
    assert set(choice.scores) == {"conductance", "rest_conductance"}
    assert choice.only == "the conductance kinds: u9 declares another circuit"
    # and without such a unit every kind competes
    assert candidates(DIVIDER) == ["volts", "rest_volts", "conductance", "rest_conductance"]


def test_on_one_unit_the_choice_is_by_trial_on_the_validation_split():
    # given: one unit (a transimpedance front end: volts linear in conductance), train and val trials
    rows = _units(Transimpedance(circuit="transimpedance", drive_v=1.0, feedback_kohm=47.0), {"u1": 0.01})
    train, val = rows[rows.trial_id != "t3"], rows[rows.trial_id == "t3"]
    choice = choose_inputs(LEAST_SQUARES, train, val, CHANNELS, None, rest_s=0.5)
    assert choice.folds == "by trial: train split -> validation split"
    # the output is linear in the load above the preload's offset: rest_volts takes the offset out
    assert choice.chosen == "rest_volts"


def test_fit_records_the_choice_and_a_pinned_kind_records_none():
    rows = _units(DIVIDER, UNITS)
    train, val = rows[rows.unit_id != "u3"], rows[rows.unit_id == "u3"]
    auto = fit("ls", LSParams(), train, val, front_end=DIVIDER)
    assert auto.checkpoint["inputs"]["kind"] == auto.metrics["inputs"] == "rest_conductance"
    assert auto.checkpoint["inputs"]["front_end"] == DIVIDER.model_dump(mode="json")
    assert auto.checkpoint["inputs_choice"]["chosen"] == "rest_conductance"
    pinned = fit("ls", LSParams(inputs=InputParams(kind="volts")), train, val, front_end=DIVIDER)
    assert pinned.checkpoint["inputs_choice"] is None and pinned.checkpoint["inputs"]["front_end"] is None


def test_a_pinned_conductance_without_a_circuit_says_what_to_declare():
    rows = _units(DIVIDER, {"u1": 0.01})
    with pytest.raises(ValueError, match=r"sensor\.front_end"):
        fit("fnn", FNNParams(max_epochs=1, inputs=InputParams(kind="rest_conductance")), rows)


def test_the_choice_is_deterministic():
    rows = _units(DIVIDER, UNITS, seed=3)
    a = choose_inputs(LSTM_15, rows, rows.iloc[:0], CHANNELS, DIVIDER, 0.5)
    b = choose_inputs(LSTM_15, rows, rows.iloc[:0], CHANNELS, DIVIDER, 0.5)
    assert a == b and "lags [3, 7] samples" in a.stand_in


def _angle(scores: dict[str, float | None], folds: str = "leave-one-unit-out (3 units)") -> Choice:
    return Choice(min((v, k) for k, v in scores.items() if v is not None)[1], scores, folds, "ridge")


def test_one_kind_for_all_angles_by_the_mean_score_though_one_angle_prefers_another():
    # given: two angles where the rest kinds are near-tied and each angle prefers another
    by_angle = {
        "0": _angle({"volts": 12.0, "rest_volts": 7.9, "rest_conductance": 8.2}),
        "15": _angle({"volts": 12.6, "rest_volts": 7.8, "rest_conductance": 7.7}),
    }
    # when: pooling them
    choice = pool(by_angle)
    # then: the kind of the lower mean, with the means and each angle's own scores recorded
    assert by_angle["15"].chosen == "rest_conductance"
    assert choice.chosen == "rest_volts"
    assert choice.scores == {"volts": 12.3, "rest_volts": 7.85, "rest_conductance": 7.95}
    assert choice.folds == "leave-one-unit-out (3 units), at each of 2 angles, scores averaged"


def test_a_kind_that_is_not_a_candidate_at_every_angle_is_not_chosen():
    # given: conductance scored well at one angle only (the other declares no circuit)
    by_angle = {"0": _angle({"volts": 9.0, "conductance": 1.0}), "15": _angle({"volts": 9.0})}
    # when / then: only the common kind competes; none in common is a located error
    assert pool(by_angle).chosen == "volts" and list(pool(by_angle).scores) == ["volts"]
    with pytest.raises(ValueError, match="at every angle: 0°: conductance; 15°: volts"):
        pool({"0": _angle({"conductance": 1.0}), "15": _angle({"volts": 9.0})})


def test_the_choice_file_round_trips_and_names_itself_when_wrong(tmp_path):
    # given: the choose stage's file for lstm, and a pinned one for ls
    chosen = pool({"0": _angle({"volts": 9.0, "rest_volts": 5.0})})
    save_choice(tmp_path / "lstm.json", "lstm", chosen)
    save_choice(tmp_path / "ls.json", "ls", None, pinned="volts")
    # when / then: read back as written; another kind's file or garbage says which file
    assert load_choice(tmp_path / "lstm.json", "lstm") == replace(chosen, scores={})  # the decision
    assert load_choice(tmp_path / "ls.json", "ls") is None
    with pytest.raises(ValueError, match=r"lstm\.json.*not fnn's inputs choice"):
        load_choice(tmp_path / "lstm.json", "fnn")
    (tmp_path / "bad.json").write_text("{")
    with pytest.raises(ValueError, match=r"bad\.json: not a readable inputs choice.*run the choose stage"):
        load_choice(tmp_path / "bad.json", "ls")
