"""What the deployed model's tests build: a registered champion and its calibrated unit, what a
simulator sends for a trial, and the Python client's force on it."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from needlecue_client import ForceClient
from needlecue_runtime.features import InputTransform, unit_inputs
from needlecue_runtime.frontend import Divider
from pipeline.config import InputParams
from pipeline.modelling import export
from pipeline.modelling.fit import fit
from pipeline.modelling.kinds.lstm import LSTMParams
from tests.client.builders import cue_trials, keep_axes, register, register_unit, unit_document

CIRCUIT = Divider(circuit="divider", supply_v=5.0, fixed_kohm=10.0, series_kohm=1.5)
MIX = [[1.08, 0.05, 0.0], [0.0, 0.93, 0.04], [-0.03, 0.0, 1.1]]
UNIT = "est-d1"


@dataclass(frozen=True)
class Champion:
    uri: str  # the store needle-force-30@champion and needle-unit-est-d1@current are registered in
    checkpoint: dict
    doc: dict  # the unit's calibration document
    trial: pd.DataFrame  # a held-out trial of the unit


def registered_champion(uri: str, root: Path, axes: tuple[str, ...] | None = None) -> Champion:
    """A 30° LSTM on rest-relative volts as needle-force-30@champion in store `uri` (artifacts under `root`),
    a unit calibrated with it on its FSRs' conductance, and a held-out trial of that unit. `axes`: the
    model of those axes alone (`keep_axes`: a reference that recorded only them), else of all three."""
    inputs = InputParams(kind="rest_volts")
    params = LSTMParams(window=6, hidden=6, max_epochs=3, patience=2, batch_size=64, inputs=inputs)
    checkpoint = fit("lstm", params, cue_trials(30, 3)).checkpoint
    if axes is not None:
        checkpoint = keep_axes(checkpoint, axes)
    register(uri, root, checkpoint)
    doc = unit_document(UNIT, {30: checkpoint}, MIX)
    doc["front_end"] = CIRCUIT.model_dump(mode="json")
    doc["transforms"]["lstm"]["domain"] = "conductance"
    register_unit(uri, doc)
    return Champion(uri, checkpoint, doc, cue_trials(30, 1, "unit-d1", seed=11, n=90))


def client_forces(c: Champion, cache: Path) -> np.ndarray:
    """The Python client's force on every sample of the trial, for the calibrated unit."""
    client = ForceClient.from_registry(30, unit_id=UNIT, cache_dir=cache, tracking_uri=c.uri)
    assert client.calibrated
    volts, t = c.trial[list(client.channels)].to_numpy(), c.trial["t_s"].to_numpy()
    return np.array([client.step(v, float(s)).force_n for v, s in zip(volts, t, strict=True)])


def pyfunc_champion(c: Champion) -> Any:
    """The registered champion through MLflow's own loader (what `mlflow models serve` serves)."""
    import mlflow

    mlflow.set_tracking_uri(c.uri)
    mlflow.set_registry_uri(c.uri)
    return mlflow.pyfunc.load_model("models:/needle-force-30@champion")


def raw_feed(c: Champion) -> dict[str, np.ndarray]:
    """What a simulator sends for every sample of the trial: its raw windows, rest readings and unit."""
    transform = InputTransform.from_dict(c.doc["transforms"]["lstm"], CIRCUIT)
    volts, t = c.trial[c.checkpoint["channels"]].to_numpy(), c.trial["t_s"].to_numpy()
    unit = unit_inputs(transform, CIRCUIT, 3)
    return export.graph_feed(c.checkpoint, volts, t, np.arange(len(volts)), unit)
