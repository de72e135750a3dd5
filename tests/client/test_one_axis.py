"""A model of the axes its reference recorded (issue 56): a load cell's model of fz alone gives one
force per sample, named fz, through the client and replay, never a stand-in for fx or fy; and a
description whose `targets` are not a subset of fx, fy, fz in that order is refused in one line."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

import needlecue_client as fc
from needlecue_client.replay import plot_replay, replay, rmse
from pipeline.cli import app
from pipeline.modelling.fit import fit
from pipeline.modelling.predictor import Predictor
from tests.client.builders import CHANNELS, TINY, Registered, cue_trials, keep_axes, register
from tests.projects import new_store

pytestmark = pytest.mark.filterwarnings("ignore::needlecue_client.force.UncalibratedUnit")


@pytest.fixture(scope="module")
def fz_folder(registered: Registered, empty_store: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The registered LSTM as the model of fz alone (its very fz weights), registered without a cue
    pack in a store of its own and fetched."""
    root = tmp_path_factory.mktemp("fz-registry")
    uri = new_store(empty_store, root)
    register(uri, root, keep_axes(registered.checkpoint, ("fz",)))
    return fc.fetch(30, cache_dir=root / "cache", tracking_uri=uri)


def test_a_model_of_fz_gives_one_force_per_sample_named_fz(fz_folder: Path, fetched: Path) -> None:
    # given: the model of fz alone, and the three-axis model it was cut from
    one, three = fc.ForceClient.from_dir(fz_folder), fc.ForceClient.from_dir(fetched)
    trial = cue_trials(30, 1, seed=5, n=40)
    volts, t = trial[CHANNELS].to_numpy(), trial["t_s"].to_numpy()
    # when: both step through a trial
    frames = [one.step(v, float(s)) for v, s in zip(volts, t, strict=True)]
    full = np.array([three.step(v, float(s)).force_n for v, s in zip(volts, t, strict=True)])
    # then: one value per sample, named fz by the client, the three-axis model's fz
    assert one.targets == ("fz",) and three.targets == ("fx", "fy", "fz")
    assert all(f.force_n.shape == (1,) for f in frames)
    np.testing.assert_allclose([f.force_n[0] for f in frames], full[:, 2], rtol=0, atol=1e-5)


def test_replay_of_a_model_of_fz_writes_fz_alone(fz_folder: Path, tmp_path: Path) -> None:
    # given: the model of fz alone, and a recorded trial whose reference has all three axes
    client = fc.ForceClient.from_dir(fz_folder)
    trial = cue_trials(30, 1, seed=6, n=50)
    # when: replaying it, and plotting the replay
    out = replay(trial, client)
    png = plot_replay(out, tmp_path / "fz.png", "fz only")
    # then: the prediction and the reference of fz, no column for fx or fy; its RMSE alone; a plot
    assert list(out.columns) == ["t_s", "fz", "fz_ref", "cue", "angle_est_deg", "reason"]
    np.testing.assert_allclose(out["fz_ref"], trial["fz"])
    assert set(rmse(out)) == {"fz"} and out["cue"].isna().all()
    assert png.is_file() and png.stat().st_size > 0


def test_replay_command_of_a_model_of_fz_reports_fz(fz_folder: Path, tmp_path: Path) -> None:
    # given: a processed parquet of one trial and the model of fz as a fetched folder
    data = tmp_path / "external.parquet"
    cue_trials(30, 1, "held", seed=3).to_parquet(data)
    # when: `needlecue replay --model-dir`
    png = tmp_path / "plot.png"
    result = CliRunner().invoke(app, ["replay", str(data), "--model-dir", str(fz_folder), "--out", str(png)])
    # then: the RMSE of fz alone
    assert result.exit_code == 0, result.output
    rmse_line = next(line for line in result.output.splitlines() if line.startswith("RMSE vs reference"))
    assert rmse_line.startswith("RMSE vs reference: fz ") and "fx" not in rmse_line and png.is_file()


def test_a_cue_pack_profiling_other_axes_than_the_model_gives_force_without_cues(
    registered: Registered, mlflow_store: str, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    # given: the model of fz alone registered with the three-axis model's cue pack (its standard
    # profile is of fx, fy, fz)
    uri = mlflow_store
    register(uri, tmp_path, keep_axes(registered.checkpoint, ("fz",)), registered.pack)
    # when: the client loads it and steps
    with caplog.at_level("WARNING", logger="needlecue_client"):
        client = fc.ForceClient.from_registry(
            30, cache_dir=tmp_path / "cache", tracking_uri=uri, cues_uncalibrated=True
        )
    frame = client.step([0.3, 0.3, 0.3], 0.0)
    # then: its force, no cues, and a warning naming both sets of axes
    assert frame.force_n.shape == (1,) and frame.cue is None and not client.has_cues
    assert any(
        "standard profile is of ['fx', 'fy', 'fz'], the model gives ['fz']" in m for m in caplog.messages
    )


def _set_targets(text: str, value: str) -> str:
    """The MLmodel text with needlecue.targets (a YAML list of items) set to the YAML `value`."""
    lines = text.splitlines(keepends=True)
    start = next(i for i, line in enumerate(lines) if line.startswith("    targets:"))
    end = start + 1
    while end < len(lines) and lines[end].startswith("    - "):
        end += 1
    return "".join([*lines[:start], f"    targets: {value}\n", *lines[end:]])


@pytest.mark.parametrize(
    "value", ["[fz, fx]", "[]", "[fw]", "fz", "[fz, fz]", "[fx, fy, fz, fz]", "[Fz]", "null"]
)
def test_a_description_whose_targets_are_not_axes_in_order_is_one_line_naming_the_field(
    fz_folder: Path, tmp_path: Path, value: str
) -> None:
    # given: the fz model's folder with its targets changed to something that is not a subset of
    # fx, fy, fz in that order
    folder = shutil.copytree(fz_folder, tmp_path / "model")
    (folder / "MLmodel").write_text(_set_targets((folder / "MLmodel").read_text(), value))
    # when / then: one line naming the file and the field, verified or not
    for unverified in (False, True):
        with pytest.raises(
            fc.ModelFolderError, match=r"field needlecue\.targets is .*; expected a non-empty"
        ) as e:
            fc.ForceClient.from_dir(folder, unverified=unverified)
        assert str(folder / "MLmodel") in str(e.value) and "\n" not in str(e.value)


def test_a_description_naming_other_axes_than_its_graph_gives_is_refused(
    fz_folder: Path, tmp_path: Path
) -> None:
    # given: the fz model's folder whose description claims all three axes
    folder = shutil.copytree(fz_folder, tmp_path / "model")
    (folder / "MLmodel").write_text(_set_targets((folder / "MLmodel").read_text(), "[fx, fy, fz]"))
    # when / then: verified, the description is not the registered one; unverified, the graph's
    # single column does not match the three it names
    with pytest.raises(fc.ModelRefused, match=r"needlecue\.targets differs from the graph's own"):
        fc.ForceClient.from_dir(folder)
    with pytest.raises(ValueError, match=r"output force_n of shape \['batch', 1\] does not match"):
        fc.ForceClient.from_dir(folder, unverified=True)


@pytest.mark.parametrize("kind", ["ls", "lstm"])
def test_a_model_trained_on_fz_alone_is_registered_and_run_as_one_force(
    kind: str, mlflow_store: str, tmp_path: Path
) -> None:
    # given: a model trained on trials whose reference recorded fz alone, registered and fetched
    train = cue_trials(30, 3).drop(columns=["fx", "fy"])
    checkpoint = fit(kind, TINY[kind], train).checkpoint
    uri = mlflow_store
    register(uri, tmp_path, checkpoint)
    client = fc.ForceClient.from_registry(30, cache_dir=tmp_path / "cache", tracking_uri=uri)
    # when: the client steps through a held-out trial
    trial = cue_trials(30, 1, seed=9, n=40)
    volts, t = trial[CHANNELS].to_numpy(), trial["t_s"].to_numpy()
    got = np.array([client.step(v, float(s)).force_n for v, s in zip(volts, t, strict=True)])
    # then: one force per sample, fz, the trained model's own
    expected = Predictor(checkpoint).predict(trial.drop(columns=["fx", "fy", "fz"]))
    assert checkpoint["targets"] == ["fz"] and client.targets == ("fz",) and got.shape == (40, 1)
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-4)
