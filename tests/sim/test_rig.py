"""The rig simulator writes deterministic rig-log/1 folders."""

from __future__ import annotations

import pandas as pd
import pytest
import yaml

from pipeline.config import SimulateParams
from pipeline.rig.format import BatchMeta
from pipeline.sim import rig
from tests.helpers import tree_hash

SMALL = SimulateParams(angles_deg=(15, 45), train_batches=1, trials_per_angle=2, heldout_trials_per_angle=1)


def test_writes_one_training_cast_and_a_heldout_batch_per_angle(tmp_path):
    # When the simulator runs on a small plan
    ids = rig.run(SMALL, tmp_path / "sim")
    # Then it writes a training cast and one held-out batch per angle
    assert ids == ["sim-tissue-1", "sim-heldout-15deg", "sim-heldout-45deg"]
    batch = tmp_path / "sim" / "sim-tissue-1"
    meta = BatchMeta.model_validate(yaml.safe_load((batch / "batch.yaml").read_text()))
    assert meta.batch_id == "sim-tissue-1" and meta.sensor.units == "counts"
    trials = pd.read_csv(batch / "trials.csv")
    assert sorted(trials.angle_deg.unique()) == [15, 45]
    # And every trial has both streams in the format's columns, counts inside the ADC range
    for trial_id in trials.trial_id:
        fsr = pd.read_csv(batch / f"{trial_id}.fsr.csv")
        ref = pd.read_csv(batch / f"{trial_id}.ref.csv")
        assert list(fsr.columns) == ["t_ms", "fsr1", "fsr2", "fsr3"]
        assert list(ref.columns) == ["t_s", "fx", "fy", "fz"]
        assert fsr[["fsr1", "fsr2", "fsr3"]].stack().between(0, 1023).all()
        assert fsr.t_ms.is_monotonic_increasing and ref.t_s.is_monotonic_increasing


def test_same_params_same_bytes(tmp_path):
    rig.run(SMALL, tmp_path / "a")
    rig.run(SMALL, tmp_path / "b")
    assert tree_hash(tmp_path / "a") == tree_hash(tmp_path / "b")
    rig.run(SMALL.model_copy(update={"seed": 1}), tmp_path / "c")
    assert tree_hash(tmp_path / "a") != tree_hash(tmp_path / "c")


def test_disabled_writes_only_the_manifest(tmp_path):
    assert rig.run(SMALL.model_copy(update={"enabled": False}), tmp_path / "sim") == []
    assert [p.name for p in (tmp_path / "sim").iterdir()] == [rig.MANIFEST]


def test_refuses_to_clear_a_folder_it_did_not_write(tmp_path):
    # Given a folder holding someone's data
    (tmp_path / "lab").mkdir()
    (tmp_path / "lab" / "precious.csv").write_text("1,2,3\n")
    # Then the simulator will not write into it, and leaves it alone
    with pytest.raises(FileExistsError, match="not written by the simulator"):
        rig.run(SMALL, tmp_path / "lab")
    assert (tmp_path / "lab" / "precious.csv").read_text() == "1,2,3\n"
