"""Building the cue packs from training splits only: per preset angle, the standard profile and the
paper-method thresholds (`pipeline.cues.thresholds`), and the angle estimator shared by every preset
(`pipeline.cues.estimator`). The pack is checked and written as a `needlecue_runtime.cues.pack.CuePack`.

What cannot be built from the data (the angle estimator: one angle only, too few trials, no rest
reading; the standard profile: no trial with a contact) is left null and `unavailable` says why; the
tracker falls back to what the pack has.
"""

from __future__ import annotations

import json
import math
import time
import warnings
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np
import pandas as pd

from needlecue_runtime.cues.pack import FORMAT, sig
from needlecue_runtime.frontend import circuit_key
from needlecue_runtime.vocab import angle_name, channels_of
from pipeline.config import CuesParams
from pipeline.cues.estimator import Circuits, try_fit_angle_estimator
from pipeline.cues.thresholds import Predicted, paper_thresholds, standard_profile
from pipeline.cues.trials import Trial, trials_of, trials_rate_hz
from pipeline.logs import Log


def build_cue_pack(
    train_by_angle: Mapping[float, pd.DataFrame],
    preset_angle: float,
    params: CuesParams,
    predicted: Predicted | None = None,
    log: Log | None = None,
    angle_estimator: Mapping[str, Any] | None = None,
    *,
    estimator_unavailable: str | None = None,
    circuits: Circuits | None = None,
) -> dict[str, Any]:
    """The cue pack of one preset angle, from training splits only (see the module docstring).

    `train_by_angle`: every angle's training frame (the angle estimator needs them all).
    `predicted`: {kind: {angle: forces}}, the preset angle's model of each kind on every angle's
    training frame (rows in frame order), used to calibrate the paper-method thresholds per kind;
    None calibrates them on the reference force alone (an ideal model).
    `angle_estimator`: a `fit_angle_estimator` result to reuse (it is the same for every preset);
    `estimator_unavailable`: why there is none (then none is fitted). Without either, it is fitted here.
    `circuits`: {unit_id: its declared circuit}; the pack records the one its training units share.

    What cannot be built from the data (the angle estimator: one angle only, too few trials, no rest
    reading; the standard profile: no trial with a contact) is left null, and `unavailable` says why
    (the key is there only then); `CueTracker` falls back to what the pack has.
    """
    log = log or (lambda _m: None)
    train_by_angle = {float(a): f for a, f in train_by_angle.items()}
    preset = float(preset_angle)
    if preset not in train_by_angle or train_by_angle[preset].empty:
        raise ValueError(f"no training data for the preset angle {preset:g}°")
    channels = channels_of(train_by_angle[preset])
    if not channels:
        raise ValueError("the training frames have no estimator channel")
    for a, f in train_by_angle.items():
        if channels_of(f) != channels:
            raise ValueError(f"angle {a:g}° has channels {channels_of(f)}, the preset has {channels}")
    angles = sorted(train_by_angle)
    trials = {a: trials_of(train_by_angle[a], channels, a, circuits) for a in angles}
    rate = trials_rate_hz(trials[preset])
    unavailable: dict[str, str] = {}

    try:
        profile: dict[str, Any] | None = standard_profile(trials[preset], params)[0]
    except ValueError as e:
        profile = None
        unavailable["standard_profile"] = str(e)
        log(f"warning: preset {preset:g}°: no standard profile ({e}): no paper-method cue in its pack")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN reference force
        norms = [np.nanmax(np.linalg.norm(tr.force, axis=1)) for tr in trials[preset] if len(tr.t)]
    peak = float(np.nanmax(norms)) if norms and np.isfinite(norms).any() else math.nan

    predicted = dict(predicted or {})
    for kind, by_angle in predicted.items():
        if missing := [angle_name(a) for a in angles if a not in by_angle]:
            raise ValueError(
                f"no {kind} predictions of the {preset:g}° model on the training frames of {missing}"
            )
    thresholds: dict[str, Any] = {}
    if profile is not None:
        thresholds, missing = paper_thresholds(trials, preset, profile, predicted, params, log)
        unavailable.update(missing)

    estimator: dict[str, Any] | None
    if angle_estimator is not None:
        estimator = dict(angle_estimator)
    elif estimator_unavailable is not None:
        estimator = None
    else:
        estimator, estimator_unavailable = try_fit_angle_estimator(train_by_angle, params, log, circuits)
    if estimator is None:
        unavailable["angle_estimator"] = estimator_unavailable or "not fitted"
    pack = {
        "format": FORMAT,
        "preset_angle_deg": preset,
        "angles": angles,
        "channels": list(channels),
        "rate_hz": sig(rate) if math.isfinite(rate) else None,
        "standard_profile": profile,
        "angle_estimator": estimator,
        "thresholds": {
            "profile": thresholds,
            "force_limit_n": sig(params.force_margin * peak) if math.isfinite(peak) else None,
            "continue_below_deg": float(params.continue_below_deg),
            "stop_from_deg": float(params.stop_from_deg),
        },
        "training": {
            "trials_per_angle": {angle_name(a): len(trials[a]) for a in angles},
            "batches": sorted({tr.batch for a in angles for tr in trials[a]}),
        },
        "params": params.model_dump(mode="json"),
        # the circuit the training units share (their loading directions are in its conductance)
        "front_end": _shared_circuit(trials, angles),
    }
    if unavailable:
        pack["unavailable"] = dict(sorted(unavailable.items()))
    return pack


def _shared_circuit(
    trials: Mapping[float, Sequence[Trial]], angles: Sequence[float]
) -> dict[str, Any] | None:
    """The circuit every training trial's unit declares, as stored (None if any declares none or
    they differ: then the directions of a unit without its own are read in volts)."""
    found = {circuit_key(tr.front_end) for a in angles for tr in trials[a]}
    return json.loads(found.pop()) if len(found) == 1 and "" not in found else None


def build_packs(
    train_by_angle: Mapping[float, pd.DataFrame],
    predicted_for: Callable[[float], Predicted],
    params: CuesParams,
    log: Log,
    circuits: Circuits | None = None,
) -> dict[float, dict[str, Any]]:
    """The cue pack of every angle with training rows; `predicted_for(preset)` gives that preset's
    models' predictions on every angle's training frame ({kind: {angle: forces}}); `circuits` is
    {unit_id: its declared circuit}."""
    estimator, no_estimator = try_fit_angle_estimator(train_by_angle, params, log, circuits)
    packs: dict[float, dict[str, Any]] = {}
    for preset in train_by_angle:
        started = time.perf_counter()
        packs[preset] = build_cue_pack(
            train_by_angle,
            preset,
            params,
            predicted_for(preset) or None,
            log=log,
            angle_estimator=estimator,
            estimator_unavailable=no_estimator,
            circuits=circuits,
        )
        log(f"pack for {angle_name(preset)}° built ({time.perf_counter() - started:.1f} s)")
    return packs
