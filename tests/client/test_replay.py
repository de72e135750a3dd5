"""Replaying a recorded trial through the client: one row per sample, the cue timeline and the RMSE."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import needlecue_client as fc
from needlecue_client.replay import cue_changes, replay, rmse
from pipeline.config import CuesParams
from pipeline.cues.packs import build_cue_pack
from pipeline.modelling.fit import fit
from tests.client.builders import BENCH_UNIT, TINY, cue_predictions, cue_trials, register

pytestmark = pytest.mark.filterwarnings("ignore::needlecue_client.force.UncalibratedUnit")


def test_replay_returns_one_row_per_sample_in_time_order(fetched: Path) -> None:
    # given: one trial at the preset angle, its rows shuffled
    # the training unit, whose evidence is in the pack: its cues without a calibration of its own
    client = fc.ForceClient.from_dir(fetched, unit_id=BENCH_UNIT, cues_uncalibrated=True)
    trial = cue_trials(30, 1, seed=4, n=60)
    shuffled = trial.sample(frac=1.0, random_state=0)
    # when: replaying it
    out = replay(shuffled, client)
    # then: t_s ascending, predictions beside the reference, the RMSE per axis, and the cue per sample,
    # ending on "continue" at the estimated preset angle
    assert list(out.columns) == [
        "t_s",
        "fx",
        "fy",
        "fz",
        "fx_ref",
        "fy_ref",
        "fz_ref",
        "cue",
        "angle_est_deg",
        "reason",
    ]
    assert out["t_s"].is_monotonic_increasing and len(out) == 60
    np.testing.assert_allclose(out["fx_ref"], trial["fx"])
    assert set(rmse(out)) == {"fx", "fy", "fz"}
    assert out["cue"].iloc[0] == "wait" and (out["cue"].iloc[-1], out["angle_est_deg"].iloc[-1]) == (
        "continue",
        30,
    )
    assert list(cue_changes(out)["cue"]) == ["wait", "continue"]
    with pytest.raises(ValueError, match="one trial at a time"):
        replay(cue_trials(30, 2, n=10), client)
    with pytest.raises(fc.StreamMismatch, match="lacks column"):
        replay(trial.drop(columns="fsr2"), client)


def test_a_cue_pack_without_an_angle_estimator_cues_by_the_profile(tmp_path: Path, mlflow_store: str) -> None:
    # given: an LS model registered with the pack of a project trained at one angle only (no angle
    # estimator can be fitted: the pack has none, and says why)
    train = pd.concat([cue_trials(30, 3, "b1"), cue_trials(30, 3, "b2", seed=1)], ignore_index=True)
    checkpoint = fit("ls", TINY["ls"], train).checkpoint
    pack = build_cue_pack({30: train}, 30, CuesParams(), cue_predictions(checkpoint, {30: train}))
    assert pack["angle_estimator"] is None and "angle_estimator" in pack["unavailable"]
    register(mlflow_store, tmp_path, checkpoint, pack)
    # when: the client fetches it and replays a trial
    client = fc.ForceClient.from_registry(
        30, cache_dir=tmp_path / "cache", tracking_uri=mlflow_store, cues_uncalibrated=True
    )
    out = replay(cue_trials(30, 1, "held", seed=7), client)
    # then: it has cues, from the paper's profile method, each saying that the angle estimate is unavailable
    assert client.has_cues
    assert out["angle_est_deg"].isna().all() and out["cue"].notna().all()
    assert out["reason"].str.startswith("angle estimate unavailable").all()
    assert out["cue"].iloc[-1] in ("continue", "correct", "stop")
