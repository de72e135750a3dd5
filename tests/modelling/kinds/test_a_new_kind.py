"""A model kind is one module: a ridge regression defined here, put in the table and nowhere else,
trains, is evaluated, exports to ONNX, is registered and is served by the simulator's client."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest
import torch
from pydantic import Field

import needlecue_client as fc
from needlecue_runtime.features import ModelInputs
from needlecue_runtime.vocab import AXES
from pipeline.config import InputParams, Section
from pipeline.logs import Log
from pipeline.metrics.scores import axis_scores
from pipeline.modelling.checkpoint import ModelConfig, save_model_dir
from pipeline.modelling.fit import fit
from pipeline.modelling.inputs import features_of
from pipeline.modelling.kinds import TABLE
from pipeline.modelling.kinds.base import Fitted, ModelKind, StandIn, preprocessing
from pipeline.modelling.kinds.linear import LinearModel
from pipeline.modelling.predictor import load_predictor
from pipeline.modelling.split_predictions import predict_frame
from tests.client.builders import CHANNELS, cue_trials, register

pytestmark = pytest.mark.filterwarnings("ignore::needlecue_client.force.UncalibratedUnit")


class RidgeParams(Section):
    """`ridge`: its params section."""

    alpha: float = Field(1.0, gt=0)
    inputs: InputParams = InputParams(kind="volts")


class Ridge(ModelKind):
    """Ridge regression on the inputs, centred, with an intercept: the whole of a new kind."""

    name = "ridge"
    params = RidgeParams

    def config(self, params: RidgeParams, n_in: int) -> ModelConfig:
        return ModelConfig(self.name, n_in)

    def stand_in(self, params: RidgeParams) -> StandIn:
        return StandIn(linear=True)

    def train(
        self,
        cfg: ModelConfig,
        params: RidgeParams,
        spec: ModelInputs,
        train: pd.DataFrame,
        val: pd.DataFrame,
        channels: list[str],
        log: Log,
    ) -> Fitted:
        x, y = features_of(train, channels, spec), train[list(AXES)].to_numpy(np.float64)
        xc, yc = x - x.mean(axis=0), y - y.mean(axis=0)
        weight = np.linalg.solve(xc.T @ xc + params.alpha * np.eye(x.shape[1]), xc.T @ yc).T
        bias = y.mean(axis=0) - x.mean(axis=0) @ weight.T
        state = {"weight": torch.from_numpy(weight), "bias": torch.from_numpy(bias)}
        n, m = len(channels), len(AXES)
        summary = {"epochs_run": 1, "best_epoch": 1, "best_val_loss": None, "early_stopping": False}
        history = [{"epoch": 1, "train_loss": math.nan, "val_loss": math.nan}]
        identity = preprocessing(np.zeros(n), np.ones(n), np.zeros(m), np.ones(m))  # inputs as they are
        return Fitted(state, identity, history, summary)

    def load(self, cfg: ModelConfig, state: dict[str, Any], preprocessing: dict[str, Any]) -> LinearModel:
        return LinearModel(state["weight"], state["bias"])


@pytest.fixture
def ridge_kind(monkeypatch: pytest.MonkeyPatch) -> None:
    """The one line a new kind adds to `pipeline.modelling.kinds.TABLE`."""
    monkeypatch.setitem(TABLE, Ridge.name, Ridge())


def _mean_nrmse(pred: np.ndarray, frame: pd.DataFrame) -> float:
    return float(np.mean([s["nrmse_pct"] for s in axis_scores(pred, frame[list(AXES)].to_numpy()).values()]))


def test_a_kind_not_in_the_table_is_refused_by_name() -> None:
    # given: no ridge in the table; when / then: training one names the kinds there are
    with pytest.raises(ValueError, match=r"cannot train model kind 'ridge'; expected one of ls, fnn, lstm"):
        fit("ridge", RidgeParams(), cue_trials(30, 2))


def test_a_kind_added_to_the_table_alone_trains_evaluates_exports_and_is_served(
    ridge_kind: None, mlflow_store: str, tmp_path: Path
) -> None:
    # given: training and unseen trials at 30°
    train = pd.concat([cue_trials(30, 3, "b1"), cue_trials(30, 3, "b2", seed=1)], ignore_index=True)
    unseen = cue_trials(30, 2, "b9", seed=7)
    # when: it is trained and saved as the train stage saves a model, and loaded as the predict stage does
    result = fit("ridge", RidgeParams(alpha=1e-3), train)
    save_model_dir(tmp_path / "model", result.checkpoint, result.metrics, result.history)
    predictor = load_predictor(tmp_path / "model")
    predicted = predict_frame(predictor, unseen, "ridge on unseen trials")
    # then: it is evaluated like the other kinds, and beats predicting the training mean
    assert (predictor.kind, predictor.sequence, predictor.window) == ("ridge", False, 1)
    assert result.metrics["kind"] == "ridge" and result.checkpoint["inputs"]["kind"] == "volts"
    mean_force = np.tile(train[list(AXES)].to_numpy().mean(axis=0), (len(unseen), 1))
    assert _mean_nrmse(predicted, unseen) < 0.5 * _mean_nrmse(mean_force, unseen)

    # when: it is exported, registered as champion and fetched by the simulator's client
    uri = mlflow_store
    register(uri, tmp_path, result.checkpoint)
    client = fc.ForceClient.from_dir(fc.fetch(30, cache_dir=tmp_path / "cache", tracking_uri=uri))
    trial = unseen[unseen.trial_id == "t00"]
    samples = zip(trial[CHANNELS].to_numpy(), trial["t_s"], strict=True)
    streamed = [client.step(volts, t).force_n for volts, t in samples]
    # then: the client serves its forces, those of the checkpoint, to float32 precision
    assert client.kind == "ridge" and client.window == 1
    expected = predicted[unseen.trial_id.to_numpy() == "t00"]
    np.testing.assert_allclose(np.array(streamed), expected, rtol=0, atol=1e-5 * np.abs(expected).max())
