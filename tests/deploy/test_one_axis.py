"""A registered model of fz alone (issue 56: the lab's reference recorded one axis) outside the
client: its graph has one output column, its MLmodel's description and signature say so, and MLflow's
own pyfunc gives one force per row, the client's."""

from __future__ import annotations

from pathlib import Path

import mlflow
import numpy as np
import onnxruntime as ort
import pytest
import yaml

from pipeline.modelling import export
from tests.deploy.builders import Champion, client_forces, pyfunc_champion, raw_feed


def _downloaded(c: Champion, tmp_path: Path) -> Path:
    mlflow.set_tracking_uri(c.uri)
    mlflow.set_registry_uri(c.uri)
    return Path(
        mlflow.artifacts.download_artifacts("models:/needle-force-30@champion", dst_path=str(tmp_path))
    )


def test_the_graph_of_a_model_of_fz_has_one_column_and_its_description_says_fz(
    fz_champion: Champion, tmp_path: Path
) -> None:
    # given: the registered model of fz alone, as MLflow stores it
    folder = _downloaded(fz_champion, tmp_path)
    mlmodel = yaml.safe_load((folder / "MLmodel").read_text())
    # when: onnxruntime runs its graph on a held-out trial's raw readings
    session = ort.InferenceSession(str(folder / "model.onnx"), providers=["CPUExecutionProvider"])
    feed = raw_feed(fz_champion)
    got = session.run(None, feed)[0]
    # then: (n, 1) forces, the graph and the description naming fz; the signature one column wide
    out = session.get_outputs()[0]
    assert (out.name, out.shape, got.shape) == ("force_n", ["batch", 1], (len(feed["reading"]), 1))
    assert mlmodel["metadata"]["needlecue"]["targets"] == ["fz"]
    assert '"targets": ["fz"]' in session.get_modelmeta().custom_metadata_map["needlecue"]
    signature = yaml.safe_load(mlmodel["signature"]["outputs"])
    assert signature == [
        {"type": "tensor", "tensor-spec": {"dtype": "float32", "shape": [-1, 1]}, "name": "force_n"}
    ]
    assert export.describe(fz_champion.checkpoint).endswith(
        "Returns `force_n` float32 (batch, 1): fz in N. docs/deploy.md."
    )


def test_pyfunc_of_a_model_of_fz_gives_one_force_per_row(fz_champion: Champion, tmp_path: Path) -> None:
    # given: the model of fz alone, its calibrated unit, and a held-out trial of the unit's raw readings
    feed = raw_feed(fz_champion)
    # when: MLflow's own loader runs it (what `mlflow models serve` serves), and the client steps
    got = np.asarray(pyfunc_champion(fz_champion).predict(feed)["force_n"])
    expected = client_forces(fz_champion, tmp_path / "cache")
    # then: one column, fz, the client's within 1e-5 N
    assert got.shape == (len(feed["reading"]), 1) and expected.shape == got.shape
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-5)


@pytest.mark.parametrize("targets", [["fz", "fx"], [], ["fz", "fz"], ["f"]])
def test_a_checkpoint_whose_targets_are_not_axes_in_order_is_not_exported(
    fz_champion: Champion, targets: list[str]
) -> None:
    # given / when / then: the checkpoint's targets edited to something that is not a subset of
    # fx, fy, fz in that order: no description, no graph
    bad = dict(fz_champion.checkpoint, targets=targets)
    with pytest.raises(
        ValueError, match=r"the checkpoint's targets are .*: expected a non-empty list of force axes"
    ):
        export.deploy_metadata(bad, None)
    with pytest.raises(ValueError):
        export.to_onnx(bad)


def test_a_checkpoint_naming_more_axes_than_its_network_gives_is_not_exported(fz_champion: Champion) -> None:
    # given: the one-output network's checkpoint claiming all three axes
    bad = dict(fz_champion.checkpoint, targets=["fx", "fy", "fz"])
    # when / then: the graph is refused, naming what it gives and what was claimed
    with pytest.raises(
        ValueError, match=r"gives 1 force column\(s\), its checkpoint's targets are \['fx', 'fy', 'fz'\]"
    ):
        export.to_onnx(bad)
