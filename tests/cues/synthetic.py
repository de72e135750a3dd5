"""Synthetic trials for the cue tests: an estimator whose rest reading and loading direction depend
on the insertion angle, so the angle can be told from the volts."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd

from needlecue_runtime.cues.pack import FORMAT
from needlecue_runtime.cues.tracker import CueTracker
from needlecue_runtime.cues.units import unit_evidence

RATE = 30.0
NOMINAL = "nominal"  # the unit that records `make_trial`'s trials unless told otherwise
CHANNELS = ("fsr1", "fsr2", "fsr3")
ANGLES = (0, 15, 30, 45)


def rest_volts(angle: float) -> np.ndarray:
    a = math.radians(angle)
    return np.array([0.50 + 0.08 * math.sin(a), 0.55 - 0.06 * math.sin(a), 0.58 + 0.02 * math.cos(a)])


def loading_direction(angle: float) -> np.ndarray:
    u = np.array([1.0 - angle / 45.0, 1.0, 0.4 + angle / 60.0])
    return u / np.linalg.norm(u)


def make_trial(
    angle: float, seed: int, batch_id: str, trial_id: str, unit: tuple[np.ndarray, np.ndarray] | None = None
) -> pd.DataFrame:
    """One insertion: rest, 4 s of insertion (loading ramps up), dwell, retraction, rest. `unit`:
    (rest gain, loading gain) per channel of the estimator unit that records it (None: the nominal)."""
    rng = np.random.default_rng(seed)
    t0 = 2.0 + rng.uniform(0, 0.3)
    t = np.arange(0, t0 + 4.0 + 0.5 + 1.5 + 1.0, 1 / RATE)
    ramp = np.clip((t - t0) / 4.0, 0, 1) * (t < t0 + 4.5) + np.clip(1 - (t - t0 - 4.5) / 1.5, 0, 1) * (
        t >= t0 + 4.5
    )
    phase = np.where(
        t < t0,
        "rest",
        np.where(
            t < t0 + 4.0,
            "insertion",
            np.where(t < t0 + 4.5, "dwell", np.where(t < t0 + 6.0, "retraction", "rest")),
        ),
    )
    a = math.radians(angle)
    force = 0.6 * ramp[:, None] * np.array([math.sin(a), 0.3, -math.cos(a)])
    rest_gain, load_gain = unit if unit is not None else (np.ones(3), np.ones(3))
    s = 0.8 * 0.6 * ramp[:, None] * loading_direction(angle) * load_gain
    gain = 1 + rng.normal(0, 0.002, 3)
    volts = rest_volts(angle) * rest_gain * gain * np.exp(s) + rng.normal(0, 0.0008, (len(t), 3))
    return pd.DataFrame(
        {
            "batch_id": batch_id,
            "trial_id": trial_id,
            "angle_deg": float(angle),
            "tissue_point": "p1",
            "unit_id": NOMINAL,
            "t_s": t,
            "phase": phase,
            **{c: volts[:, i] for i, c in enumerate(CHANNELS)},
            "fx": force[:, 0],
            "fy": force[:, 1],
            "fz": force[:, 2],
        }
    )


def make_split(angle: float, batches: list[str], per_batch: int, seed: int) -> pd.DataFrame:
    return pd.concat(
        [
            make_trial(angle, seed * 1000 + 100 * b + k + int(angle), name, f"a{angle:g}-{name}-{k}")
            for b, name in enumerate(batches)
            for k in range(per_batch)
        ],
        ignore_index=True,
    )


def draw_unit(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """An estimator unit: per channel, a rest gain (10 %: more than the angles move the rest reading)
    and a loading gain (15 %)."""
    rng = np.random.default_rng(seed)
    return 1 + rng.normal(0, 0.10, 3), 1 + rng.normal(0, 0.15, 3)


def make_unit_split(
    angle: float, unit_id: str, batches: list[str], per_batch: int, seed: int
) -> pd.DataFrame:
    """`make_split` recorded by the unit `draw_unit` of its id, with its `unit_id` column."""
    unit = draw_unit(sum(map(ord, unit_id)))
    frame = pd.concat(
        [
            make_trial(angle, seed * 1000 + 100 * b + k + int(angle), name, f"a{angle:g}-{name}-{k}", unit)
            for b, name in enumerate(batches)
            for k in range(per_batch)
        ],
        ignore_index=True,
    )
    frame["unit_id"] = unit_id
    return frame


def nominal_tracker(pack: dict, preset: float, **kw) -> CueTracker:
    """A tracker reading the nominal unit, which recorded the training trials (its evidence is in
    the pack), as the client reads a training unit."""
    return CueTracker(pack, preset, unit_evidence=unit_evidence(pack, NOMINAL), **kw)


def run_tracker(tracker: CueTracker, frame: pd.DataFrame, force: np.ndarray | None = None) -> list:
    tracker.reset()
    v = frame[list(CHANNELS)].to_numpy()
    f = frame[["fx", "fy", "fz"]].to_numpy() if force is None else force
    return [tracker.update(t, v[i], f[i]) for i, t in enumerate(frame["t_s"].to_numpy())]


def end_of_insertion(trial: pd.DataFrame) -> int:
    return int(np.flatnonzero(trial["phase"].to_numpy() == "insertion")[-1])


def zero_forces(external: dict[float, pd.DataFrame]):
    """forces_of for `evaluate_cues`: a stand-in model that predicts no force at all."""
    return lambda _kind, _preset, angle: np.zeros((len(external[angle]), 3))


def external_split(per_angle: int) -> dict[float, pd.DataFrame]:
    """Held-out trials per angle of ANGLES (what `write_processed` puts in external.parquet)."""
    return {float(a): make_split(a, ["heldout"], per_angle, seed=9) for a in ANGLES}


def write_processed(root, train_by_angle: dict[float, pd.DataFrame], external_per_angle: int):
    for a, train in train_by_angle.items():
        folder = root / f"{a:g}"
        folder.mkdir(parents=True, exist_ok=True)
        train.to_parquet(folder / "train.parquet", index=False)
        make_split(a, ["heldout"], external_per_angle, seed=9).to_parquet(
            folder / "external.parquet", index=False
        )
    return root


def whole_pack(estimator: dict | None = None, preset: float = 30.0) -> dict:
    """A whole cue pack (every field the typed document requires) around a hand-made angle
    estimator: its stages and the estimator completed with neutral values where not given."""
    if estimator is not None:
        stage = {
            "template_weight": None,
            "offset_spread": None,
            "temperature": 1.0,
            "temperatures": {},
            "outside_limit": None,
            "n_train": 0,
            "cv_accuracy": None,
        }
        estimator = {
            "method": "hand-made",
            "features": "hand-made",
            "classes_deg": [],
            "levels": [],
            "units": {},
            "cv": "none",
            "confidence": {},
            **estimator,
            "stages": [{**stage, **s} for s in estimator.get("stages", [])],
        }
    return {
        "format": FORMAT,
        "preset_angle_deg": preset,
        "angles": [float(a) for a in ANGLES],
        "channels": list(CHANNELS),
        "rate_hz": RATE,
        "standard_profile": None,
        "angle_estimator": estimator,
        "thresholds": {
            "profile": {},
            "force_limit_n": None,
            "continue_below_deg": 7.5,
            "stop_from_deg": 22.5,
        },
        "training": {"trials_per_angle": {}, "batches": []},
        "params": {},
        "front_end": None,
    }
