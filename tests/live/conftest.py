"""Fixtures of the live tests: a tiny 30° model with a cue pack, registered with a calibrated unit,
and rig-log/1 estimator files of synthetic insertions (1 s at rest, then loading) at chosen angles."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from needlecue_client import fetch
from pipeline.config import CuesParams
from pipeline.cues.packs import build_cue_pack
from pipeline.modelling.fit import fit
from tests.client.builders import (
    CHANNELS,
    TINY,
    cue_evidence,
    cue_predictions,
    cue_trials,
    keep_axes,
    register,
    register_unit,
    unit_document,
)
from tests.projects import new_store

UNIT = "est-live"
ADC_BITS = 12
VREF = 5.0


@dataclass(frozen=True)
class LiveModel:
    uri: str  # the store it is registered in, with UNIT's calibration
    model_dir: Path  # the champion, fetched


@pytest.fixture(scope="package")
def live_model(empty_store: Path, tmp_path_factory: pytest.TempPathFactory) -> LiveModel:
    root = tmp_path_factory.mktemp("live-registry")
    uri = new_store(empty_store, root)
    angles = (0, 15, 30, 45, 60, 75)
    train = {
        a: pd.concat([cue_trials(a, 3, "b1"), cue_trials(a, 3, "b2", seed=1)], ignore_index=True)
        for a in angles
    }
    checkpoint = fit("ls", TINY["ls"], train[30]).checkpoint
    pack = build_cue_pack(train, 30, CuesParams(), cue_predictions(checkpoint, train))
    register(uri, root, checkpoint, pack)
    # the unit's calibration insertions read as the training unit's trials (the same synthetic unit)
    register_unit(uri, unit_document(UNIT, {30: checkpoint}, cues=cue_evidence(pack)))
    return LiveModel(uri, fetch(30, cache_dir=root / "cache", tracking_uri=uri))


@pytest.fixture(scope="package")
def fz_live_model(empty_store: Path, tmp_path_factory: pytest.TempPathFactory) -> LiveModel:
    """The champion of a lab whose reference recorded fz alone (a 30° LS of fz, no cue pack), fetched."""
    root = tmp_path_factory.mktemp("live-fz-registry")
    uri = new_store(empty_store, root)
    train = pd.concat([cue_trials(30, 3, "b1"), cue_trials(30, 3, "b2", seed=1)], ignore_index=True)
    register(uri, root, keep_axes(fit("ls", TINY["ls"], train).checkpoint, ("fz",)))
    return LiveModel(uri, fetch(30, cache_dir=root / "cache", tracking_uri=uri))


def write_trials(
    folder: Path, angles: list[float], seed: int = 7, adc_bits: int = ADC_BITS, withdraw: bool = False
) -> list[Path]:
    """A rig-log/1 batch of one synthetic trial per angle (held-out draws: another seed than training),
    in `adc_bits` counts; the estimator files, in the order of `angles`. With `withdraw`, each trial ends
    with the needle out: its first second at rest, twice. A synthetic trial ends loaded and
    its rest reading moves about 13 % per 15° (the simulator's: about 3 %), so trials played back to
    back should be at most 15° apart: the insertion detector ends a steady stretch within 20 % of rest."""
    folder.mkdir(parents=True)
    meta = {
        "format": "rig-log/1",
        "batch_id": folder.name,
        "sensor": {
            "unit_id": UNIT,
            "channels": CHANNELS,
            "units": "counts",
            "adc_bits": adc_bits,
            "vref_v": VREF,
        },
        "reference": {"units": "N"},
    }
    (folder / "batch.yaml").write_text(yaml.safe_dump(meta))
    rows, paths = [], []
    for k, angle in enumerate(angles):
        trial = cue_trials(angle, 1, folder.name, seed=seed + k)
        if withdraw:
            rest = trial[trial["t_s"] < 1.0]
            step = trial["t_s"].iloc[1]
            tail = [
                rest.assign(t_s=rest["t_s"] + trial["t_s"].iloc[-1] + step * (1 + i * len(rest)))
                for i in (0, 1)
            ]
            trial = pd.concat([trial, *tail], ignore_index=True)
        tid = f"a{angle:g}-t{k:02d}"
        counts = np.rint(trial[CHANNELS].to_numpy() / VREF * (2**adc_bits - 1)).astype(int)
        fsr = pd.DataFrame(counts, columns=CHANNELS)
        fsr.insert(0, "t_ms", (trial["t_s"].to_numpy() * 1000).round(3))
        fsr.to_csv(folder / f"{tid}.fsr.csv", index=False)
        trial[["t_s", "fx", "fy", "fz"]].to_csv(folder / f"{tid}.ref.csv", index=False)
        rows.append({"trial_id": tid, "angle_deg": angle, "tissue_point": f"p{k}"})
        paths.append(folder / f"{tid}.fsr.csv")
    pd.DataFrame(rows).to_csv(folder / "trials.csv", index=False)
    return paths
