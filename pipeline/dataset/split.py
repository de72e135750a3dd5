"""Splitting the resampled trials per angle into train/val/test by trial, with held-out batches
as the external set: the trials read (`pipeline.dataset.trials`), each placed by the rules below
(`pipeline.dataset.split_plan`), and the files written here.

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

import json
import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import pyarrow as pa

from needlecue_runtime.frontend import circuit_key, declared
from needlecue_runtime.vocab import AXES, CALIBRATION, SPLITS
from pipeline.config import SplitParams
from pipeline.dataset.split_plan import AngleSplit, drop_repeats, plan, plan_calibration, untrainable
from pipeline.dataset.splits import FRONT_ENDS
from pipeline.dataset.tables import columns_for, table_schema, write_table
from pipeline.dataset.trials import Trial, load_trials
from pipeline.logs import Log

MANIFEST = "manifest.json"

logger = logging.getLogger(__name__)


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
