"""Splitting the resampled trials per angle into train/val/test by trial, with held-out batches
as the external set.

Input: the resample stage's `IN_DIR/<batch_id>.parquet` + `<batch_id>.json`. Output, per
angle (folder `vocab.angle_name`): `train.parquet`, `val.parquet`, `test.parquet`,
`external.parquet` (always all four; empty with the right schema when there is nothing);
`calibration/<angle>.parquet` for each angle with calibration trials (same schema as the
angle's split files); `front_ends.json` in each angle folder and in `calibration/`: the circuit
each unit with trials there declares (batch.yaml `sensor.front_end`, null if none), which every
feature that needs a circuit reads; and `OUT_DIR/manifest.json` listing which trial went where, and
each estimator unit's batches, role (`training` if it has rows in a train split, else `new`) and
front end.

Rules:
- trials of batches with `purpose: calibration` (a new unit's short calibration session) go to
  `calibration/` only, never to train/val/test/external, whatever the external globs say; nothing
  about them reaches the angle folders, so adding a calibration batch leaves those byte-identical;
- trials of batches matching a glob of `split.external_batches` form `external`;
- the others are split by trial, never by sample (samples of one trial are strongly
  correlated, so a split by sample would leak), with a generator seeded from
  (`split.seed`, angle) alone over the sorted trial list: adding data to one angle never
  changes another angle's files;
- each recording is used once: a trial whose samples (estimator channels and forces, whatever
  their names) equal an earlier trial's, in (batch, trial) order, is set aside naming that trial,
  so a batch copied under another name, a held-out one included, is never trained on and scored
  at once;
- one angle, one channel list: trials whose channels differ from the majority's are set
  aside (a model per angle takes one fixed input vector); calibration trials must have the
  channels of their angle's other trials (the majority of calibration trials where there are
  none);
- one angle, one set of force axes (docs/rig-log-format.md, `reference.axes`): an angle's models
  are trained on the axes every one of its batches records; the axes some batches record beyond
  those are left out of its files and named in the manifest (`axes_left_out`), the log and the
  ledger. Trials that share no axis with the angle's majority are set aside. A calibration batch
  keeps the axes both it and its angle's models have.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
from collections import Counter
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, replace
from fnmatch import fnmatchcase
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from pipeline.config import SplitParams
from pipeline.dataset.splits import FRONT_ENDS
from pipeline.dataset.tables import columns_for, table_schema, write_table
from pipeline.frontend import circuit_key, declared
from pipeline.logs import Log
from pipeline.rig.repeats import SAMPLES_KEY, reason, repeats
from pipeline.vocab import AXES, CALIBRATION, SPLITS, angle_name, axes_of, sorted_angles

MANIFEST = "manifest.json"

TrialKey = tuple[str, str]  # (batch_id, trial_id)

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class Trial:
    """One resampled trial: its rows and what the split needs to know about it."""

    batch_id: str
    trial_id: str
    angle: str  # folder name, vocab.angle_name(angle_deg)
    channels: tuple[str, ...]
    table: pa.Table
    axes: tuple[str, ...] = AXES  # the force axes its reference recorded
    unit_id: str = ""  # the estimator unit that recorded the batch
    purpose: str = "training"  # the batch's purpose: training | calibration
    front_end: dict[str, Any] | None = None  # the batch's batch.yaml sensor.front_end, as declared
    samples_sha256: str = ""  # its samples' hash from ingest (`pipeline.rig.repeats`)

    @property
    def key(self) -> TrialKey:
        return (self.batch_id, self.trial_id)


def load_trials(in_dir: Path) -> tuple[list[Trial], float | None]:
    """Every trial of every resampled batch, and the grid rate they share."""
    trials: list[Trial] = []
    rates: set[float] = set()
    for data_path in sorted(in_dir.glob("*.parquet")):
        meta_path = data_path.with_suffix(".json")
        if not meta_path.is_file():
            raise FileNotFoundError(f"{data_path}: no {meta_path.name} next to it (channels, rate_hz)")
        meta = json.loads(meta_path.read_text())
        channels = tuple(str(c) for c in meta["channels"])
        rates.add(float(meta["rate_hz"]))
        table = pq.read_table(data_path)
        axes = axes_of(table.column_names)
        if not axes:
            raise ValueError(f"{data_path}: no force column (one of {list(AXES)}) among {table.column_names}")
        missing = [c for c in columns_for(channels, axes) if c not in table.column_names]
        if missing:
            raise ValueError(f"{data_path}: columns {missing} missing (channels from {meta_path.name})")
        table = table.select(columns_for(channels, axes))
        if not isinstance(meta.get(SAMPLES_KEY), dict):
            raise ValueError(f"{meta_path}: no {SAMPLES_KEY} (written by an older resample: run dvc repro)")
        purpose = str(meta.get("purpose") or "training")
        batch = _split_by_trial(str(meta["batch_id"]), channels, table, purpose, meta.get("front_end"))
        missing_hash = sorted(t.trial_id for t in batch if t.trial_id not in meta[SAMPLES_KEY])
        if missing_hash:
            raise ValueError(f"{meta_path}: trials {missing_hash} have no {SAMPLES_KEY} entry")
        trials += [replace(t, samples_sha256=str(meta[SAMPLES_KEY][t.trial_id])) for t in batch]
    if len(rates) > 1:
        raise ValueError(f"resampled batches disagree on the grid rate: {sorted(rates)} Hz")
    return sorted(trials, key=lambda t: t.key), (rates.pop() if rates else None)


def _split_by_trial(
    batch_id: str, channels: tuple[str, ...], table: pa.Table, purpose: str, front_end: dict[str, Any] | None
) -> list[Trial]:
    ids = np.asarray(table.column("trial_id").to_pylist(), dtype=object)
    if ids.size == 0:
        return []
    order = np.argsort(ids.astype(str), kind="stable")
    sorted_ids = ids[order]
    cuts = np.flatnonzero(sorted_ids[1:] != sorted_ids[:-1]) + 1
    out = []
    for rows in np.split(order, cuts):
        part = table.take(pa.array(rows))
        angle = angle_name(part.column("angle_deg")[0].as_py())
        unit = str(part.column("unit_id")[0].as_py())
        axes = axes_of(part.column_names)
        out.append(Trial(batch_id, str(ids[rows[0]]), angle, channels, part, axes, unit, purpose, front_end))
    return out


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


def split_table(trials: list[Trial], schema: pa.Schema) -> pa.Table:
    """Rows of the given trials in their (sorted) order, or an empty table of that schema."""
    if not trials:
        return schema.empty_table()
    return pa.concat_tables([t.table.cast(schema) for t in trials])


def _schema(trials: list[Trial], channels: tuple[str, ...], axes: tuple[str, ...]) -> pa.Schema:
    """The schema of a file of these trials: the first one's, else the documented one."""
    if trials:
        return trials[0].table.select(columns_for(channels, axes)).schema.remove_metadata()
    return table_schema(channels, axes)


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


def run(
    in_dir: Path,
    out_dir: Path,
    p: SplitParams,
    *,
    trained: Sequence[float] | None = None,
    log: Log = logger.info,
) -> dict[str, Any]:
    """Write every angle's four split files, the calibration files and the manifest; returns the
    manifest. With `trained` (the angles models are trained at), ValueError before writing anything if
    one of them has no training trial (`untrainable`)."""
    trials, rate_hz = load_trials(in_dir)
    circuits = unit_front_ends(trials)  # ValueError before anything is written if a unit's disagree
    trials, copies = drop_repeats(trials)
    angles = plan([t for t in trials if t.purpose != CALIBRATION], p)
    if trained is not None and (why := untrainable(angles, trained)):
        raise ValueError(why)
    calibration = plan_calibration(
        [t for t in trials if t.purpose == CALIBRATION],
        {a.angle: a.channels for a in angles},
        {a.angle: a.axes for a in angles},
    )
    out_dir.mkdir(parents=True, exist_ok=True)
    manifest: dict[str, Any] = {"rate_hz": rate_hz, "angles": {}, "set_aside": list(copies)}
    schemas: dict[str, pa.Schema] = {}
    for a in angles:
        schema = schemas[a.angle] = _schema([t for ts in a.splits.values() for t in ts], a.channels, a.axes)
        entry: dict[str, Any] = {"channels": list(a.channels), "splits": {}, "n_samples": {}, "n_trials": {}}
        if a.axes != AXES:  # absent: all three (a manifest of three-axis data reads as before)
            entry["axes"] = list(a.axes)
        if a.axes_left_out:
            entry["axes_left_out"] = a.axes_left_out
        for name in SPLITS:
            table = split_table(a.splits[name], schema)
            write_table(table, out_dir / a.angle / f"{name}.parquet")
            entry["splits"][name] = [{"batch_id": t.batch_id, "trial_id": t.trial_id} for t in a.splits[name]]
            entry["n_samples"][name] = table.num_rows
            entry["n_trials"][name] = len(a.splits[name])
        manifest["angles"][a.angle] = entry
        _write_front_ends(out_dir / a.angle, [t for ts in a.splits.values() for t in ts], circuits)
        manifest["set_aside"] += a.set_aside
        log(_angle_table(a.angle, entry, len(a.set_aside)))
        for batch, extra in sorted(a.axes_left_out.items()):
            log(
                f"split: warning: angle {a.angle}: {batch} records {', '.join(extra)} too, which other "
                f"batches of the angle do not: its models estimate {', '.join(a.axes)} only"
            )
        if not entry["n_trials"]["external"]:
            log(
                f"split: warning: angle {a.angle} has no external trials (no usable trial of a batch "
                f"matching split.external_batches {list(p.external_batches)}): its models are scored on "
                "the test split, trials of the training batches, not on data never seen in training"
            )
    manifest["calibration"] = {}
    angle_axes = {a.angle: a.axes for a in angles}
    for c in calibration:
        if c.trials:  # the angle's schema, so that the calibration rows read like its split files
            schema = schemas.get(c.angle) if c.angle in schemas and c.axes == angle_axes[c.angle] else None
            schema = schema or _schema(c.trials, c.channels, c.axes)
            write_table(split_table(c.trials, schema), out_dir / CALIBRATION / f"{c.angle}.parquet")
            manifest["calibration"][c.angle] = [
                {"batch_id": t.batch_id, "trial_id": t.trial_id, "unit_id": t.unit_id} for t in c.trials
            ]
        manifest["set_aside"] += c.set_aside
        units = sorted({t.unit_id for t in c.trials})
        log(f"split: calibration, angle {c.angle}: {len(c.trials)} trials (units {', '.join(units) or '-'})")
        for batch, extra in sorted(c.axes_left_out.items()):
            log(f"split: warning: calibration, angle {c.angle}: {batch}'s {', '.join(extra)} not used")
        if c.axes_left_out:
            manifest.setdefault("calibration_axes_left_out", {})[c.angle] = c.axes_left_out
    calibrating = [t for c in calibration for t in c.trials]
    if calibrating:
        _write_front_ends(out_dir / CALIBRATION, calibrating, circuits)
    manifest["units"] = _units(trials, angles)
    for unit, entry in manifest["units"].items():
        entry["front_end"] = circuits.get(unit)
    _remove_stale(out_dir, {a.angle for a in angles}, set(manifest["calibration"]))
    (out_dir / MANIFEST).write_text(json.dumps(manifest, indent=2, sort_keys=True) + "\n")
    for s in manifest["set_aside"]:
        log(f"split: set aside {s['batch_id']}/{s['trial_id']}: {s['reason']}")
    return manifest


def _angle_table(angle: str, entry: dict[str, Any], n_aside: int) -> str:
    """The progress lines of one angle: its channels, then trials and samples per split."""
    axes = f"; forces {', '.join(entry['axes'])}" if "axes" in entry else ""
    channels = ", ".join(entry["channels"])
    lines = [f"split: angle {angle} (channels {channels}{axes}; {n_aside} trials set aside)"]
    lines.append(f"  {'split':<9}{'trials':>7}{'samples':>10}")
    for name in SPLITS:
        lines.append(f"  {name:<9}{entry['n_trials'][name]:>7}{entry['n_samples'][name]:>10}")
    return "\n".join(lines)


def _units(trials: list[Trial], angles: list[AngleSplit]) -> dict[str, dict[str, Any]]:
    """Each estimator unit's batches, and its role: `training` if it has rows in a train split."""
    trained = {t.unit_id for a in angles for t in a.splits["train"] if t.table.num_rows}
    batches: dict[str, set[str]] = {}
    for t in trials:
        batches.setdefault(t.unit_id, set()).add(t.batch_id)
    return {
        unit: {"role": "training" if unit in trained else "new", "batches": sorted(ids)}
        for unit, ids in sorted(batches.items())
    }


def unit_front_ends(trials: list[Trial]) -> dict[str, dict[str, Any] | None]:
    """{unit_id: the circuit its batches declare (batch.yaml sensor.front_end), or None}: a batch that
    declares none (or `circuit: none`) takes its unit's from the unit's other batches. ValueError,
    naming the batches, if two batches of one unit declare different circuits."""
    seen: dict[str, dict[str, tuple[str, ...]]] = {}
    for t in trials:
        circuit = declared(t.front_end)
        if circuit is not None:
            key = circuit_key(circuit)
            seen.setdefault(t.unit_id, {}).setdefault(key, ())
            if t.batch_id not in seen[t.unit_id][key]:
                seen[t.unit_id][key] += (t.batch_id,)
    out: dict[str, dict[str, Any] | None] = {t.unit_id: None for t in trials}
    for unit, by_circuit in seen.items():
        if len(by_circuit) > 1:
            listed = "; ".join(f"{', '.join(b)}: {c}" for c, b in sorted(by_circuit.items()))
            raise ValueError(
                f"unit {unit!r}: its batches declare different front ends ({listed}); one unit has one "
                "circuit (batch.yaml sensor.front_end): give a rebuilt unit a new sensor.unit_id"
            )
        out[unit] = json.loads(next(iter(by_circuit)))
    return dict(sorted(out.items()))


def _write_front_ends(folder: Path, trials: list[Trial], circuits: dict[str, dict[str, Any] | None]) -> None:
    """FRONT_ENDS in `folder`: the circuit of every unit with trials there (null: none declared)."""
    units = sorted({t.unit_id for t in trials})
    folder.mkdir(parents=True, exist_ok=True)
    (folder / FRONT_ENDS).write_text(
        json.dumps({u: circuits.get(u) for u in units}, indent=2, sort_keys=True) + "\n"
    )


def _remove_stale(out_dir: Path, angles: set[str], calibration: set[str]) -> None:
    """Drop angle folders and calibration files of an earlier run that this run does not write
    (only our own files)."""
    ours = {f"{name}.parquet" for name in SPLITS} | {FRONT_ENDS}
    for d in sorted(out_dir.iterdir()):
        if d.name == CALIBRATION:
            continue
        if d.is_dir() and d.name not in angles and {f.name for f in d.iterdir()} <= ours:
            for f in d.iterdir():
                f.unlink()
            d.rmdir()
    folder = out_dir / CALIBRATION
    if folder.is_dir():
        for f in sorted(folder.glob("*.parquet")):
            if f.is_file() and f.stem not in calibration:
                f.unlink()
        if not calibration:
            (folder / FRONT_ENDS).unlink(missing_ok=True)
        if not any(folder.iterdir()):
            folder.rmdir()
