"""Which trial goes where, in memory (the rules are in `pipeline.dataset.split`): each recording once,
per angle one channel list and one set of force axes, the external batches held out, the others cut
into train/val/test by a generator seeded from (`split.seed`, angle) alone."""

from __future__ import annotations

import hashlib
import math
from collections import Counter
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, replace
from fnmatch import fnmatchcase

import numpy as np

from needlecue_runtime.vocab import AXES, angle_name, sorted_angles
from pipeline.config import SplitParams
from pipeline.dataset.tables import columns_for
from pipeline.dataset.trials import Trial, TrialKey
from pipeline.rig.repeats import reason, repeats


def drop_repeats(trials: list[Trial]) -> tuple[list[Trial], list[dict[str, str]]]:
    """The trials with each recording once (the first in (batch, trial) order), and the set-aside
    record of every repeat (`pipeline.rig.repeats`, as `needlecue check` finds them)."""
    found = repeats({t.key: t.samples_sha256 for t in trials})
    kept = [t for t in sorted(trials, key=lambda t: t.key) if t.key not in found]
    aside = [
        {"angle": t.angle, "batch_id": t.batch_id, "trial_id": t.trial_id, "reason": reason(found[t.key])}
        for t in sorted(trials, key=lambda t: t.key)
        if t.key in found
    ]
    return kept, aside


def is_external(batch_id: str, globs: Iterable[str]) -> bool:
    """Whether a batch is held out (case-sensitive glob match, the same on every OS)."""
    return any(fnmatchcase(batch_id, g) for g in globs)


def angle_rng(seed: int, angle: str) -> np.random.Generator:
    """Generator from (seed, angle) only, stable across Python runs and platforms."""
    digest = hashlib.sha256(f"needlecue-split|{seed}|{angle}".encode()).digest()
    return np.random.default_rng(int.from_bytes(digest[:8], "little"))


def split_sizes(n: int, val_fraction: float, test_fraction: float) -> tuple[int, int, int]:
    """(train, val, test) trial counts: rounded half up, at least one in val and test from 3 trials."""
    n_val = math.floor(n * val_fraction + 0.5)
    n_test = math.floor(n * test_fraction + 0.5)
    if n >= 3:
        n_val, n_test = max(n_val, 1), max(n_test, 1)
    # Training always keeps at least one trial when there is any.
    while n > 0 and n_val + n_test >= n:
        if n_val >= n_test and n_val > 0:
            n_val -= 1
        else:
            n_test -= 1
    return n - n_val - n_test, n_val, n_test


def assign(keys: list[TrialKey], angle: str, p: SplitParams) -> dict[str, list[TrialKey]]:
    """Shuffle the sorted internal trials of one angle and cut them into train/val/test."""
    keys = sorted(keys)
    _, n_val, n_test = split_sizes(len(keys), p.val_fraction, p.test_fraction)
    order = angle_rng(p.seed, angle).permutation(len(keys))
    shuffled = [keys[i] for i in order]
    return {
        "test": sorted(shuffled[:n_test]),
        "val": sorted(shuffled[n_test : n_test + n_val]),
        "train": sorted(shuffled[n_test + n_val :]),
    }


def majority_channels(trials: list[Trial]) -> tuple[str, ...]:
    """Channel list of most trials (ties: the alphabetically first list, for determinism)."""
    counts = Counter(t.channels for t in trials)
    return min(counts, key=lambda ch: (-counts[ch], ch))


def common_axes(trials: list[Trial]) -> tuple[str, ...]:
    """The force axes every one of `trials` records, or, where they share none, the axes of most
    trials (ties: the first in AXES order, for determinism)."""
    shared = tuple(a for a in AXES if all(a in t.axes for t in trials))
    if shared or not trials:
        return shared
    counts = Counter(t.axes for t in trials)
    return min(counts, key=lambda axes: (-counts[axes], [AXES.index(a) for a in axes]))


def _aside(t: Trial, reason: str) -> dict[str, str]:
    """The manifest's record of a trial set aside."""
    return {"angle": t.angle, "batch_id": t.batch_id, "trial_id": t.trial_id, "reason": reason}


def _other_axes(t: Trial, axes: tuple[str, ...], whose: str) -> dict[str, str]:
    return _aside(t, f"its reference records {list(t.axes)}, no force axis of the {list(axes)} of {whose}")


def settle_axes(
    group: list[Trial], whose: str, within: tuple[str, ...] = AXES
) -> tuple[tuple[str, ...], list[Trial], list[dict[str, str]], dict[str, list[str]]]:
    """(axes, kept, set aside, left out) for one angle's trials: `common_axes` of the trials, within
    `within` (an angle's models' axes, for its calibration trials); each kept trial's table holds
    just those forces, and `left out` names, per batch, the recorded axes the angle does not use."""
    narrowed = [replace(t, axes=tuple(a for a in t.axes if a in within)) for t in group]
    axes = common_axes([t for t in narrowed if t.axes])
    kept = [t for t in narrowed if set(axes) <= set(t.axes)]
    aside = [_other_axes(t, axes, whose) for t in narrowed if not set(axes) <= set(t.axes)]
    left_out: dict[str, list[str]] = {}
    for t in group:
        if set(axes) <= set(t.axes) and (extra := [a for a in t.axes if a not in axes]):
            left_out[t.batch_id] = extra
    kept = [replace(t, axes=axes, table=t.table.select(columns_for(t.channels, axes))) for t in kept]
    return axes, kept, aside, left_out


@dataclass
class AngleSplit:
    """Everything written for one angle."""

    angle: str
    channels: tuple[str, ...]
    splits: dict[str, list[Trial]]
    set_aside: list[dict[str, str]]
    axes: tuple[str, ...] = AXES  # the force axes its models estimate
    axes_left_out: dict[str, list[str]] = field(default_factory=dict)  # {batch_id: axes it records beyond}


def _other_channels(t: Trial, channels: tuple[str, ...], whose: str) -> dict[str, str]:
    return _aside(t, f"channels {list(t.channels)} differ from the channels {list(channels)} of {whose}")


def plan(trials: list[Trial], p: SplitParams) -> list[AngleSplit]:
    """Group trials by angle, settle the channel list, and assign every trial a split (the caller
    leaves calibration trials out: see `plan_calibration`)."""
    by_angle: dict[str, list[Trial]] = {}
    for t in trials:
        by_angle.setdefault(t.angle, []).append(t)
    out = []
    for angle in sorted_angles(by_angle):
        group = by_angle[angle]
        channels = majority_channels(group)
        kept = [t for t in group if t.channels == channels]
        whose = f"the majority of trials at angle {angle}"
        aside = [_other_channels(t, channels, whose) for t in group if t.channels != channels]
        axes, kept, other_axes, left_out = settle_axes(kept, f"the trials at angle {angle}")
        aside += other_axes
        external = [t for t in kept if is_external(t.batch_id, p.external_batches)]
        internal = {t.key: t for t in kept if not is_external(t.batch_id, p.external_batches)}
        keys = assign(list(internal), angle, p)
        splits = {name: [internal[k] for k in keys[name]] for name in ("train", "val", "test")}
        splits["external"] = sorted(external, key=lambda t: t.key)
        out.append(AngleSplit(angle, channels, splits, aside, axes, left_out))
    return out


@dataclass
class AngleCalibration:
    """The calibration trials of one angle, written to `calibration/<angle>.parquet`."""

    angle: str
    channels: tuple[str, ...]
    trials: list[Trial]
    set_aside: list[dict[str, str]]
    axes: tuple[str, ...] = AXES
    axes_left_out: dict[str, list[str]] = field(default_factory=dict)


def plan_calibration(
    trials: list[Trial],
    channels_of: dict[str, tuple[str, ...]],
    axes_of_angle: dict[str, tuple[str, ...]] | None = None,
) -> list[AngleCalibration]:
    """Group calibration trials by angle; keep those with the angle's channels (`channels_of`,
    from the angle's split), or the calibration majority's at an angle with no other trials, and
    the force axes both they and the angle's models have (`axes_of_angle`)."""
    by_angle: dict[str, list[Trial]] = {}
    for t in trials:
        by_angle.setdefault(t.angle, []).append(t)
    out = []
    for angle in sorted_angles(by_angle):
        group = sorted(by_angle[angle], key=lambda t: t.key)
        if angle in channels_of:
            channels, whose = channels_of[angle], f"the trials at angle {angle}"
        else:
            channels = majority_channels(group)
            whose = f"the majority of calibration trials at angle {angle}"
        kept = [t for t in group if t.channels == channels]
        aside = [_other_channels(t, channels, whose) for t in group if t.channels != channels]
        within = (axes_of_angle or {}).get(angle, AXES)
        whose = f"the calibration trials at angle {angle}"
        axes, kept, other_axes, left_out = settle_axes(kept, whose, within)
        out.append(AngleCalibration(angle, channels, kept, aside + other_axes, axes, left_out))
    return out


def untrainable(angles: list[AngleSplit], trained: Sequence[float]) -> str | None:
    """Why the models of `trained` (params.yaml `train.angles`) cannot all be trained on this data:
    the angles without a training trial, the angles found and the params line to set; None if none."""
    have = [a.angle for a in angles if a.splits["train"]]
    missing = [angle_name(a) for a in trained if angle_name(a) not in have]
    if not missing:
        return None
    found = ", ".join(f"{a}°" for a in have) or "none"
    fix = f"train.angles: [{', '.join(have)}]" if have else "a batch with training trials under data.raw_dir"
    return (
        f"train.angles lists {', '.join(f'{a}°' for a in missing)}, but the data has no training trial "
        f"there (angles with training trials: {found}); set `{fix}` in params.yaml"
    )
