"""Shared cue fixtures: four angles of training trials, small params, the 30° pack."""

from __future__ import annotations

import pandas as pd
import pytest

from pipeline.config import CuesParams
from pipeline.cues.packs import build_cue_pack
from tests.cues.synthetic import ANGLES, make_split


@pytest.fixture(scope="module")
def train_by_angle() -> dict[float, pd.DataFrame]:
    return {float(a): make_split(a, ["b1", "b2"], 3, seed=1) for a in ANGLES}


@pytest.fixture(scope="module")
def params() -> CuesParams:
    return CuesParams(kinds=("ls",), evidence_levels=(0.05, 0.1, 0.2))


@pytest.fixture(scope="module")
def pack30(train_by_angle: dict[float, pd.DataFrame], params: CuesParams) -> dict:
    return build_cue_pack(train_by_angle, 30, params)


@pytest.fixture(scope="module")
def two_angle_pack(params: CuesParams) -> dict:
    train = {a: make_split(a, ["b1"], 3, seed=2) for a in (30.0, 45.0)}
    return build_cue_pack(train, 30, params)
