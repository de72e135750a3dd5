"""The cues scored per unit group: the training units' own external trials, and new units' read
without and with their calibration (`evaluate_unit_groups`), from the runs already tracked where the
figures are the same.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np
import pandas as pd

from needlecue_runtime.cues.evidence import UnitMap
from needlecue_runtime.cues.units import UnitEvidence
from needlecue_runtime.frontend import Circuit
from needlecue_runtime.vocab import angle_name
from pipeline.config import CuesParams
from pipeline.cues.score import Tracked, evaluate_cues
from pipeline.cues.summary import summarise_runs

UNIT_GROUPS = ("same_unit", "new_uncalibrated", "new_calibrated")
GROUP_KEYS = ("balanced_within_s", "recall_within_s", "within_s", "accuracy_final", "confusion_final", "seen")
# (kind, preset angle, true angle, split) -> the preset model's forces on that angle's `split` frame
ForcesOfSplit = Callable[[str, float, float, str], np.ndarray | None]


def _group_mask(
    frame: pd.DataFrame, group: str, roles: Mapping[str, str], calibrated: Mapping[str, bool]
) -> np.ndarray:
    if "unit_id" not in frame.columns:
        return np.zeros(len(frame), dtype=bool)
    units = frame["unit_id"].astype(str)
    if group == "same_unit":
        return units.map(lambda u: roles.get(u) == "training").to_numpy(bool)
    return units.map(lambda u: roles.get(u, "new") != "training" and bool(calibrated.get(u))).to_numpy(bool)


def evaluate_unit_groups(
    external: Mapping[float, pd.DataFrame],
    units: Mapping[str, UnitEvidence],
    params: CuesParams,
    packs: Mapping[float, Mapping[str, Any]],
    forces_of: ForcesOfSplit,
    uncalibrated_split: str,
    roles: Mapping[str, str],
    calibrated: Mapping[str, bool],
    circuits: Mapping[str, Circuit | None] | None = None,
    tracked: Tracked | None = None,
    maps: Mapping[str, UnitMap] | None = None,
) -> dict[str, Any]:
    """The cues scored per unit group: the training units' external trials (`same_unit`), and the
    external trials of new units that have a calibration, without it (`new_uncalibrated`: the angle
    estimator reads them as the average unit's, forces from `uncalibrated_split`) and with it
    (`new_calibrated`: `units` holds their calibrations' evidence, `maps` the maps some are read
    through). Per group, kind and method:
    balanced accuracy within `cue_within_s`, per-cue recall, final confusion matrix.

    `tracked`: the runs of `evaluate_cues` on all of `external` (the external forces, `units`,
    `circuits`), whose trials of the same-unit and calibrated groups are then summarised, not
    replayed: the same figures, for a third of the tracker's work."""
    out: dict[str, Any] = {}
    source = {float(a): f for a, f in external.items()}
    if (
        tracked is not None
        and tracked.skipped is None
        and set(tracked.trials) != {a for a, f in source.items() if len(f)}
    ):
        raise ValueError(
            f"the tracked runs are of angles {sorted(tracked.trials)}, not of these external trials"
        )
    for group in UNIT_GROUPS:
        masks = {a: _group_mask(f, group, roles, calibrated) for a, f in source.items()}
        frames = {a: source[a][m].reset_index(drop=True) for a, m in masks.items() if m.any()}
        if not frames:
            continue
        members = sorted({str(u) for f in frames.values() for u in f["unit_id"].unique()})
        if tracked is not None and tracked.skipped is None and group != "new_uncalibrated":
            out[group] = _group_of(tracked, set(members), sorted(frames), params)
            continue
        split = uncalibrated_split if group == "new_uncalibrated" else "external"

        def forces(
            kind: str, preset: float, a: float, split: str = split, masks: dict = masks
        ) -> np.ndarray | None:
            full = forces_of(kind, preset, a, split)
            if full is None and split != "external":  # that model had no calibration for these units
                full = forces_of(kind, preset, a, "external")
            return None if full is None else full[masks[a]]

        calibrated_now = group != "new_uncalibrated"  # an uncalibrated unit has neither evidence nor map
        ev = evaluate_cues(
            frames,
            params,
            packs,
            forces,
            log=lambda _m: None,
            units=units if calibrated_now else {},
            circuits=circuits,
            maps=maps if calibrated_now else None,
        )
        out[group] = {
            "units": members,
            "external_trials": ev.get("external_trials"),
            "results": _group_results(ev.get("results") or {}),
        }
    return out


def _group_of(
    tracked: Tracked, members: set[str], angles: Sequence[float], params: CuesParams
) -> dict[str, Any]:
    """A unit group's figures from the runs of its `members`' trials at `angles`, as `evaluate_cues`
    on those trials alone gives them."""
    trials = {a: [tr for tr in tracked.trials.get(a, ()) if tr.unit in members] for a in angles}
    if not any(trials.values()):  # nothing with an insertion to score: a skipped evaluation's fields
        return {"units": sorted(members), "external_trials": None, "results": {}}
    runs = [r for r in tracked.runs if r.unit in members and r.true_angle in trials]
    summary = summarise_runs(runs, params.continue_below_deg, params.stop_from_deg, params.cue_within_s)
    return {
        "units": sorted(members),
        "external_trials": {angle_name(a): len(trials[a]) for a in angles},
        "results": _group_results(summary),
    }


def _group_results(results: Mapping[str, Mapping[str, Mapping[str, Any]]]) -> dict[str, Any]:
    return {
        kind: {m: {k: r.get(k) for k in GROUP_KEYS} for m, r in methods.items()}
        for kind, methods in results.items()
    }
