"""The force models: determinism, no-leak scaling, self-describing checkpoints, trial-bound windows, LS."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

from needlecue_runtime.vocab import KINDS
from pipeline.config import InputParams
from pipeline.modelling.checkpoint import ModelConfig, save_checkpoint
from pipeline.modelling.fit import fit
from pipeline.modelling.inputs import sequence_order, window_index
from pipeline.modelling.kinds.fnn import FNNParams
from pipeline.modelling.kinds.ls import LSParams
from pipeline.modelling.kinds.lstm import LSTMParams
from pipeline.modelling.predictor import load_predictor
from tests.modelling.frames import CHANNELS, make_frame

VOLTS = InputParams(kind="volts")  # these tests read the channels as they are (the choice: test_choice.py)
FAST = {
    "ls": LSParams(inputs=VOLTS),
    "fnn": FNNParams(max_epochs=8, patience=3, batch_size=32, inputs=VOLTS),
    "lstm": LSTMParams(window=5, hidden=6, max_epochs=4, patience=2, batch_size=32, inputs=VOLTS),
}


@pytest.fixture(scope="module")
def train_val() -> tuple[pd.DataFrame, pd.DataFrame]:
    return make_frame(4, seed=0), make_frame(1, seed=1, batch_id="b2")


@pytest.mark.parametrize("kind", ["fnn", "lstm"])
def test_training_is_deterministic_and_seed_sensitive(kind: str, train_val) -> None:
    # given: the same data and params twice, and once with another seed
    train, val = train_val
    params = FAST[kind]
    # when: training three times
    a = fit(kind, params, train, val).checkpoint["state_dict"]
    b = fit(kind, params, train, val).checkpoint["state_dict"]
    c = fit(kind, params.model_copy(update={"seed": 1}), train, val).checkpoint["state_dict"]
    # then: the same seed gives bit-identical weights, another seed different ones
    assert a.keys() == b.keys() == c.keys()
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert not all(torch.equal(a[k], c[k]) for k in a)


@pytest.mark.parametrize("kind", ["fnn", "lstm"])
def test_weight_averaging_saves_the_running_average(kind: str, train_val) -> None:
    # given: the same training without averaging, with a tiny averaging step, and with the usual one
    train, val = train_val
    no_val = val.iloc[:0]  # all epochs run, so each variant saves its last weights
    base = FAST[kind].model_copy(update={"max_epochs": 3})
    raw = fit(kind, base, train, no_val).checkpoint["state_dict"]
    frozen = fit(kind, base.model_copy(update={"ema": 1 - 1e-9}), train, no_val).checkpoint["state_dict"]
    usual = fit(kind, base.model_copy(update={"ema": 0.9}), train, no_val).checkpoint["state_dict"]
    init = fit(kind, base.model_copy(update={"max_epochs": 1, "lr": 1e-12}), train, no_val).checkpoint
    # then: an average that barely moves keeps the initial weights; a real one is not the last iterate, and
    # is deterministic like the rest of training
    for k in raw:
        torch.testing.assert_close(frozen[k], init["state_dict"][k], rtol=0, atol=1e-6)
        assert not torch.equal(usual[k], raw[k])
    again = fit(kind, base.model_copy(update={"ema": 0.9}), train, no_val).checkpoint["state_dict"]
    assert all(torch.equal(usual[k], again[k]) for k in usual)


def test_fit_leaves_global_torch_state_alone(train_val) -> None:
    # given: a caller's own torch settings
    train, val = train_val
    threads = torch.get_num_threads()
    rng_state = torch.get_rng_state()
    # when: training
    fit("fnn", FAST["fnn"], train, val)
    # then: thread count, deterministic flag and global RNG are as before
    assert torch.get_num_threads() == threads
    assert not torch.are_deterministic_algorithms_enabled()
    assert torch.equal(torch.get_rng_state(), rng_state)


@pytest.mark.parametrize("kind", ["fnn", "lstm"])
def test_scaling_uses_training_statistics_only(kind: str, train_val) -> None:
    # given: one training split and two very different validation splits
    train, val = train_val
    other_val = make_frame(2, seed=7, batch_id="b3")
    other_val[CHANNELS] *= 3.0
    # when: training with each
    pre_a = fit(kind, FAST[kind], train, val).checkpoint["preprocessing"]
    pre_b = fit(kind, FAST[kind], train, other_val).checkpoint["preprocessing"]
    # then: the statistics are the training split's (population std) and ignore the validation rows
    np.testing.assert_array_equal(pre_a["x_mean"].numpy(), train[CHANNELS].to_numpy().mean(axis=0))
    np.testing.assert_array_equal(pre_a["x_std"].numpy(), train[CHANNELS].to_numpy().std(axis=0))
    np.testing.assert_array_equal(pre_a["y_mean"].numpy(), train[["fx", "fy", "fz"]].to_numpy().mean(axis=0))
    np.testing.assert_array_equal(pre_a["y_std"].numpy(), train[["fx", "fy", "fz"]].to_numpy().std(axis=0))
    for key in pre_a:
        assert torch.equal(pre_a[key], pre_b[key])


@pytest.mark.parametrize("kind", KINDS)
def test_checkpoint_is_self_describing_and_reproduces_predictions(
    kind: str, train_val, tmp_path: Path
) -> None:
    # given: a trained model saved to disk
    train, val = train_val
    result = fit(kind, FAST[kind], train, val, train_data_sha256="abc")
    save_checkpoint(result.checkpoint, tmp_path / "model.pt")
    # when: loading it with weights_only=True (no pickled objects allowed) and through load_predictor
    ckpt = torch.load(tmp_path / "model.pt", weights_only=True)
    predictor = load_predictor(tmp_path)
    # then: it says what it is, and predicts exactly what the freshly trained model predicted
    assert ckpt["format"] == "needlecue-model/1"
    assert ckpt["kind"] == kind
    assert ckpt["channels"] == CHANNELS
    assert ckpt["targets"] == ["fx", "fy", "fz"]
    assert ckpt["rate_hz"] == pytest.approx(30.0)
    assert ckpt["angle_deg"] == 30.0
    assert ckpt["train_data_sha256"] == "abc"
    assert ckpt["params"] == FAST[kind].model_dump(mode="json")
    assert set(ckpt["preprocessing"]) == {"x_mean", "x_std", "y_mean", "y_std"}
    assert ModelConfig.from_dict(ckpt["config"]).n_in == 3
    assert (predictor.kind, predictor.channels, predictor.angle_deg) == (kind, tuple(CHANNELS), 30.0)
    assert predictor.window == (FAST["lstm"].window if kind == "lstm" else 1)
    fresh = result.predictor.predict(val)
    assert fresh.shape == (len(val), 3)
    np.testing.assert_array_equal(predictor.predict(val), fresh)


def test_missing_channel_is_a_clear_error(train_val) -> None:
    # given: a trained model and a frame without one of its channels
    train, val = train_val
    predictor = fit("fnn", FAST["fnn"], train, val).predictor
    # when / then: predicting names the missing channel
    with pytest.raises(ValueError, match="fsr2"):
        predictor.predict(val.drop(columns=["fsr2"]))


def test_predictions_follow_the_frame_row_order(train_val) -> None:
    # given: an LSTM and the same rows shuffled
    train, val = train_val
    predictor = fit("lstm", FAST["lstm"], train, val).predictor
    frame = make_frame(3, seed=3)
    shuffled = frame.sample(frac=1.0, random_state=0)
    # when: predicting both
    y, y_shuffled = predictor.predict(frame), predictor.predict(shuffled)
    # then: each row gets the same force (windows are built in t_s order per trial), in the frame's order
    np.testing.assert_allclose(y_shuffled, y[shuffled.index.to_numpy()], rtol=0, atol=1e-12)


def test_predict_arrays_matches_predict(train_val) -> None:
    # given: a trained LSTM and a frame of several trials
    train, val = train_val
    predictor = fit("lstm", FAST["lstm"], train, val).predictor
    frame = make_frame(3, seed=4)
    # when: predicting from bare arrays with trial labels
    y = predictor.predict_arrays(frame[CHANNELS].to_numpy(), frame["trial_id"].to_numpy())
    # then: the same as from the frame
    np.testing.assert_array_equal(y, predictor.predict(frame))


def test_lstm_windows_never_cross_trials(train_val) -> None:
    # given: an LSTM and two frames that differ only in trial A's volts
    train, val = train_val
    predictor = fit("lstm", FAST["lstm"], train, val).predictor
    frame = make_frame(2, seed=5)
    changed = frame.copy()
    in_a = changed["trial_id"] == "t00"
    changed.loc[in_a, CHANNELS] += 0.3
    # when: predicting both
    y, y_changed = predictor.predict(frame), predictor.predict(changed)
    # then: trial B, its first sample included, is untouched; trial A did change
    np.testing.assert_array_equal(y[~in_a.to_numpy()], y_changed[~in_a.to_numpy()])
    assert not np.allclose(y[in_a.to_numpy()], y_changed[in_a.to_numpy()])


def test_windows_pad_with_the_trials_first_sample() -> None:
    # given: two trials of 3 and 2 rows, in sorted order
    _, start = sequence_order(np.array([0, 0, 0, 1, 1]), np.array([0.0, 1.0, 2.0, 0.0, 1.0]))
    # when: building windows of 3
    idx = window_index(start, 3)
    # then: each window ends at its row and repeats its own trial's first row before it
    assert idx.tolist() == [[0, 0, 0], [0, 0, 1], [0, 1, 2], [3, 3, 3], [3, 3, 4]]


def test_ls_has_no_intercept_and_recovers_a_linear_map() -> None:
    # given: noiseless forces that are an exact linear map of the volts
    frame = make_frame(3, seed=6)
    c = np.array([[1.5, -0.5, 0.2], [0.3, 2.0, -1.0], [-0.7, 0.1, 0.9]])
    frame[["fx", "fy", "fz"]] = frame[CHANNELS].to_numpy() @ c.T
    # when: fitting the calibration matrix
    result = fit("ls", LSParams(), frame)
    # then: C comes back, there is no bias, and zero volts read as zero force
    np.testing.assert_allclose(result.checkpoint["state_dict"]["weight"].numpy(), c, rtol=0, atol=1e-10)
    assert torch.equal(result.checkpoint["state_dict"]["bias"], torch.zeros(3, dtype=torch.float64))
    np.testing.assert_array_equal(result.predictor.predict_arrays(np.zeros((2, 3))), np.zeros((2, 3)))
    assert result.metrics["best_val_loss"] is None


def test_empty_validation_trains_all_epochs(train_val) -> None:
    # given: no validation rows
    train, val = train_val
    messages: list[str] = []
    # when: training
    result = fit("fnn", FAST["fnn"], train, val.iloc[:0], log=messages.append)
    # then: no early stopping, every epoch runs, the last weights are kept, and it says so
    assert result.metrics["epochs_run"] == result.metrics["best_epoch"] == FAST["fnn"].max_epochs
    assert result.metrics["best_val_loss"] is None
    assert any("no validation rows" in msg for msg in messages)


def test_validation_with_other_channels_is_rejected(train_val) -> None:
    # given: validation rows whose channels differ from the training rows'
    train, val = train_val
    # when / then
    with pytest.raises(ValueError, match="differ"):
        fit("fnn", FAST["fnn"], train, val.rename(columns={"fsr3": "fsr4"}))
