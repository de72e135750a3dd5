"""Reading one rig-log/1 batch folder (`docs/rig-log-format.md`): `parse_batch` reads batch.yaml,
trials.csv and every trial's two streams, validates the frames with Great Expectations and
returns what is usable plus every `Problem`. Read-only; never raises on bad input.

A bad cell sets aside its trial; a bad batch.yaml or trials.csv, or a failed check that names
no row, sets aside the whole batch. Values stay in raw units (counts or volts; the reference.axes
forces in reference.units).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from pipeline.config import IngestParams
from pipeline.rig import plausible
from pipeline.rig.batch_yaml import read_meta
from pipeline.rig.csvfile import column_index, numbers, read_csv, well_formed
from pipeline.rig.expectations import Check, Validator, frame_dt
from pipeline.rig.format import (
    BATCH_FILE,
    FSR_TIME,
    REF_TIME,
    REF_TORQUES,
    STREAM_SUFFIXES,
    TDMS,
    TDMS_INDEX,
    TRIAL_COLUMNS,
    TRIALS_FILE,
    BatchMeta,
    Problem,
    find,
    forms,
    fsr_file,
    ref_file,
    undeclared_axes,
)
from pipeline.rig.problems import ProblemLog, group_warnings
from pipeline.rig.tdmsfile import read_ref

Warn = Callable[[Path, str], None]


# --------------------------------------------------------------------------- trials.csv


@dataclass(frozen=True)
class _Trials:
    table: pd.DataFrame  # accepted rows so far, output schema
    listed: set[str]  # every trial_id string in trials.csv, good or bad (files of these are no orphans)
    extras: list[str]
    check: Check | None


def _read_trials(
    batch_dir: Path, batch_id: str, probs: ProblemLog, validator: Validator, warn: Warn, unit_id: str
) -> _Trials | None:
    """trials.csv read, checked row by row and validated with GX; None if the batch must be set aside.
    A `unit_id` column must name the batch's unit (batch.yaml `sensor.unit_id`) on every row: one
    estimator unit per batch, and a trial that names another is set aside, never relabelled."""
    path = _locate(batch_dir, TRIALS_FILE, probs, None)
    if path is None:
        return None
    file = str(path)
    table = read_csv(path, probs, None)
    if table is None:
        return None
    idx = column_index(table, TRIAL_COLUMNS, file, probs, None)
    if idx is None:
        return None
    i_id = idx["trial_id"]
    listed = {r[i_id].strip() for r in table.rows if len(r) > i_id}
    if not table.rows:
        probs.add(file, "lists no trials", line=table.header_line)
        return None
    rows, lines = well_formed(table, file, probs, lambda r: r[i_id].strip() if len(r) > i_id else None)
    extras = [h for h in table.header if h not in TRIAL_COLUMNS]
    if "" in extras:
        warn(path, "a column without a name is ignored")
        extras = [h for h in extras if h]
    ids = [r[i_id].strip() for r in rows]
    if "unit_id" in extras:
        i_unit = table.header.index("unit_id")
        for r, ln, tid in zip(rows, lines, ids, strict=True):
            if (named := r[i_unit].strip()) != unit_id:
                reason = (
                    f"unit_id {named!r}, but batch.yaml's sensor.unit_id is {unit_id!r}: a batch is "
                    "recorded with one estimator unit; put each unit's trials in a batch of its own"
                )
                probs.add(file, reason, trial_id=tid, line=ln, column="unit_id")
    # "15°" and "-0" name the angles 15 and 0 (+ 0.0 turns -0.0 into 0.0)
    degrees = [r[idx["angle_deg"]].strip().removesuffix("°") for r in rows]
    angle = numbers(degrees, lines, file, "angle_deg", ids, probs) + 0.0
    frame = pd.DataFrame(
        {
            "trial_id": pd.Series(ids, dtype=object),
            "angle_deg": angle,
            "tissue_point": pd.Series([r[idx["tissue_point"]].strip() for r in rows], dtype=object),
            "line": lines,
        }
    )
    check = None
    if len(frame):
        check = validator.trials(batch_id, frame, file)
        probs.extend(check.problems)
        if check.batch_failed:
            return None
    bad_lines = probs.bad_lines[file]
    keep = [
        i
        for i, (t, ln) in enumerate(zip(ids, lines, strict=True))
        if ln not in bad_lines and t not in probs.bad_trials
    ]
    out = pd.DataFrame(
        {
            "trial_id": [ids[i] for i in keep],
            "angle_deg": angle[keep],
            "tissue_point": [frame["tissue_point"].iat[i] for i in keep],
            **{c: [rows[i][idx[c]] for i in keep] for c in extras},
        }
    )
    # Sorted here so that every frame built from it is in trial_id order too.
    return _Trials(out.sort_values("trial_id", kind="stable", ignore_index=True), listed, extras, check)


# --------------------------------------------------------------------------- streams


def _locate(folder: Path, name: str, probs: ProblemLog, trial_id: str | None) -> Path | None:
    """The one file that is `name` in any of its forms (plain, gzip, TDMS), else None with a Problem."""
    found = find(folder, name)
    why = "" if trial_id is None else f"trial {trial_id!r} is listed in {TRIALS_FILE} but "
    if not found:
        others = " nor ".join(forms(name)[1:])
        probs.add(str(folder / name), f"{why}{name} is missing (and no {others})", trial_id=trial_id)
        return None
    if len(found) > 1:
        names = " and ".join(p.name for p in found)
        probs.add(str(found[0]), f"{names} both exist: keep one of them", trial_id=trial_id)
        return None
    if not found[0].is_file():
        probs.add(str(found[0]), f"{why}{found[0].name} is not a regular file", trial_id=trial_id)
        return None
    return found[0]


def _read_stream(
    path: Path,
    trial_id: str,
    time_col: str,
    values: Sequence[str],
    optional: Sequence[str],
    integer: bool,
    probs: ProblemLog,
    warn: Warn,
    undeclared: Mapping[str, str] | None = None,
    why: Mapping[str, str] | None = None,
) -> pd.DataFrame | None:
    """One CSV stream file as trial_id, line, time, values (+ optional columns if all present), float64.
    A column of `undeclared` in the header is a Problem (its reason), located on the header; `why`
    adds to a missing value column's reason."""
    file = str(path)
    table = read_csv(path, probs, trial_id)
    if table is None:
        return None
    required = [time_col, *values]
    idx = column_index(table, required, file, probs, trial_id, why)
    undeclared = undeclared or {}
    for c in [h for h in undeclared if h in table.header]:
        probs.add(file, undeclared[c], trial_id=trial_id, line=table.header_line, column=c)
        idx = None
    if idx is None:
        return None
    opt = [c for c in optional if c in idx]
    if opt and len(opt) != len(optional):
        warn(path, f"only {', '.join(opt)} of {', '.join(optional)} present; ignored")
        opt = []
    if extra := [h for h in table.header if h not in required and h not in optional]:
        warn(path, f"extra column(s) {', '.join(map(repr, extra))} ignored")
    if not table.rows:
        probs.add(file, "empty stream: a header but no samples", trial_id=trial_id)
        return None
    rows, lines = well_formed(table, file, probs, lambda _: trial_id, lambda msg: warn(path, msg))
    if not rows:
        return None
    cols = {
        c: numbers(
            [r[idx[c]] for r in rows], lines, file, c, trial_id, probs, integer=integer and c != time_col
        )
        for c in [*required, *opt]
    }
    return pd.DataFrame({"trial_id": pd.Series([trial_id] * len(rows), dtype=object), "line": lines, **cols})


def _rate_row(frame: pd.DataFrame, file: str, time_col: str, per_second: float) -> dict[str, Any]:
    t = frame[time_col].to_numpy()
    t = t[np.isfinite(t)]
    span = (t.max() - t.min()) / per_second if len(t) > 1 else 0.0
    # No rate without a positive span; the time checks report why.
    rate = round((len(frame) - 1) / span, 3) if span > 0 else np.nan
    return {
        "trial_id": frame["trial_id"].iat[0],
        "file": file,
        "time_column": time_col,
        "n_samples": len(frame),
        "rate_hz": rate,
    }


def _plausible_fsr(
    frame: pd.DataFrame, file: str, meta: BatchMeta, p: IngestParams, probs: ProblemLog
) -> None:
    """Volts within 0 and the ADC's reference (counts: GX checks the ADC range), not flat, no dead
    channel, no flat top, one insertion, no clock jump."""
    channels = list(meta.sensor.channels)
    if meta.sensor.units == "volts":
        unit, top = "V", plausible.volts_limit(meta, p)
        what = "V (0 to sensor.vref_v, else ingest.max_volts: counts declared as volts?)"
        plausible.check_range(frame, channels, 0.0, top, what, file, probs)
    else:  # counts declare adc_bits (batch.yaml is refused without)
        unit, top = "counts", float(2 ** (meta.sensor.adc_bits or 0) - 1)
    plausible.check_flat(frame, channels, "estimator stream", file, probs)
    plausible.check_dead(frame, channels, "estimator", file, probs)
    plausible.check_clipped(frame, channels, FSR_TIME, 1000.0, p.clip_run_s, unit, file, probs, (0.0, top))
    plausible.check_length(frame, FSR_TIME, 1000.0, meta, p, file, probs)
    plausible.check_time_steps(frame, FSR_TIME, 1000.0, "estimator stream", file, probs)


def _plausible_ref(
    frame: pd.DataFrame, file: str, meta: BatchMeta, p: IngestParams, probs: ProblemLog
) -> None:
    """Forces within the reference sensor's range, no isolated glitch, not flat, no dead axis, no flat
    top, one insertion, no clock jump: on the axes batch.yaml declares, the limits (in N) in the
    file's units."""
    forces = list(meta.reference.axes)
    unit = meta.reference.units
    limit_n = plausible.reference_limit_n(meta, p)
    top = plausible.in_units(limit_n, unit)
    in_n = "" if unit in ("N", "mN") else f"±{limit_n:g} N, "
    what = (
        f"{unit} (the reference sensor's range: {in_n}ingest.reference_max_n, or "
        "ingest.reference_max_n_by_model)"
    )
    plausible.check_range(frame, forces, -top, top, what, file, probs)
    jump = plausible.in_units(p.reference_glitch_n, unit)
    plausible.check_glitches(frame, forces, jump, unit, "ingest.reference_glitch_n", file, probs)
    plausible.check_flat(frame, forces, "reference stream", file, probs)
    plausible.check_dead(frame, forces, "reference sensor", file, probs)
    plausible.check_clipped(frame, forces, REF_TIME, 1.0, p.clip_run_s, unit, file, probs)
    plausible.check_length(frame, REF_TIME, 1.0, meta, p, file, probs)
    plausible.check_time_steps(frame, REF_TIME, 1.0, "reference stream", file, probs)


# --------------------------------------------------------------------------- one batch


@dataclass
class ParsedBatch:
    """Everything read from one batch folder: accepted frames (if any), Problems, GX results."""

    batch_id: str
    source_dir: Path
    problems: list[Problem]
    warnings: list[str]
    meta: BatchMeta | None = None
    trials: pd.DataFrame | None = None
    fsr: pd.DataFrame | None = None
    ref: pd.DataFrame | None = None
    gx: dict[str, dict[str, Any]] = field(default_factory=dict)
    trials_set_aside: list[str] = field(default_factory=list)

    @property
    def accepted(self) -> bool:
        return self.trials is not None and len(self.trials) > 0


def parse_batch(batch_dir: Path, params: IngestParams, validator: Validator) -> ParsedBatch:
    """Read and validate one batch folder (read-only). Never raises on bad input: see `.problems`."""
    batch_id = batch_dir.name
    probs = ProblemLog(batch_id)
    warnings: list[tuple[Path, str]] = []
    out = ParsedBatch(batch_id, batch_dir, [], [])

    def warn(path: Path, msg: str) -> None:
        warnings.append((path, msg))

    def done() -> ParsedBatch:
        out.problems = probs.finish()
        out.warnings = group_warnings(warnings)
        return out

    meta = read_meta(batch_dir, probs)
    if meta is None:
        return done()
    out.meta = meta
    trials = _read_trials(batch_dir, batch_id, probs, validator, warn, meta.sensor.unit_id)
    if trials is None:
        return done()
    if trials.check is not None:
        out.gx["trials"] = trials.check.result
    _orphans(batch_dir, trials.listed, probs, warn)

    channels = list(meta.sensor.channels)
    counts = meta.sensor.units == "counts"
    adc_max = 2**meta.sensor.adc_bits - 1 if counts and meta.sensor.adc_bits else None
    axes = list(meta.reference.axes)  # the force axes the reference files hold
    why = {a: f"; batch.yaml's reference.axes declares {', '.join(axes)}" for a in axes}
    fsr_frames: list[pd.DataFrame] = []
    ref_frames: list[pd.DataFrame] = []
    summary: list[dict[str, Any]] = []
    paths: dict[str, Path] = {}  # file name as rig-log/1 says it -> the file read (maybe .gz or .tdms)
    for tid in trials.table["trial_id"]:
        fsr_path = _locate(batch_dir, fsr_file(tid), probs, tid)
        if (
            fsr_path is not None
            and (f := _read_stream(fsr_path, tid, FSR_TIME, channels, (), counts, probs, warn)) is not None
        ):
            paths[fsr_file(tid)] = fsr_path
            _plausible_fsr(f, str(fsr_path), meta, params, probs)
            fsr_frames.append(f)
            summary.append(_rate_row(f, fsr_file(tid), FSR_TIME, 1000.0))
        ref_path = _locate(batch_dir, ref_file(tid), probs, tid)
        if ref_path is None:
            continue
        if ref_path.name.endswith(TDMS):
            units = meta.reference.units
            r = read_ref(ref_path, tid, units, axes, probs, lambda msg, p=ref_path: warn(p, msg))
        else:
            r = _read_stream(
                ref_path, tid, REF_TIME, axes, REF_TORQUES, False, probs, warn, undeclared_axes(axes), why
            )
        if r is not None:
            paths[ref_file(tid)] = ref_path
            _plausible_ref(r, str(ref_path), meta, params, probs)
            ref_frames.append(r)
            summary.append(_rate_row(r, ref_file(tid), REF_TIME, 1.0))

    # Torques go through only if every ref stream of the batch has them (no half-empty columns).
    torques = list(REF_TORQUES) if ref_frames and all(REF_TORQUES[0] in r for r in ref_frames) else []
    if not torques and any(REF_TORQUES[0] in r for r in ref_frames):
        warn(batch_dir, "torques ignored: not every reference stream has them")
    ref_cols = [REF_TIME, *axes, *torques]
    folder = str(batch_dir)
    checks: list[Check] = []
    fsr = ref = pd.DataFrame()
    if fsr_frames:
        fsr = pd.concat(fsr_frames, ignore_index=True)
        fsr["dt"] = frame_dt(fsr, FSR_TIME)
        checks.append(
            validator.stream(
                batch_id,
                "fsr",
                fsr,
                FSR_TIME,
                channels,
                adc_max,
                folder,
                lambda t: str(paths[fsr_file(t)]),
            )
        )
    if ref_frames:
        ref = pd.concat([r[["trial_id", "line", *ref_cols]] for r in ref_frames], ignore_index=True)
        ref["dt"] = frame_dt(ref, REF_TIME)
        checks.append(
            validator.stream(
                batch_id,
                "ref",
                ref,
                REF_TIME,
                ref_cols[1:],
                None,
                folder,
                lambda t: str(paths[ref_file(t)]),
            )
        )
    if summary:
        checks.append(
            validator.streams(batch_id, pd.DataFrame(summary), folder, lambda name: str(paths[name]))
        )
    for check in checks:
        probs.extend(check.problems)
        out.gx[check.kind] = check.result
    if any(c.batch_failed for c in checks):
        return done()

    accepted = [t for t in trials.table["trial_id"] if t not in probs.bad_trials]
    out.trials_set_aside = sorted(trials.listed - set(accepted))
    if not accepted:
        probs.add(
            str(batch_dir / TRIALS_FILE),
            f"no usable trial: all {len(trials.listed)} listed trials "
            "were set aside, so the batch is set aside",
        )
        return done()
    keep = set(accepted)
    out.trials = trials.table[trials.table["trial_id"].isin(keep)]
    out.fsr = fsr.loc[fsr["trial_id"].isin(keep), ["trial_id", FSR_TIME, *channels]]
    out.ref = ref.loc[ref["trial_id"].isin(keep), ["trial_id", *ref_cols]]
    return done()


def _orphans(batch_dir: Path, listed: set[str], probs: ProblemLog, warn: Warn) -> None:
    """Stream files without a trial row are reported (and not read); other stray files are warned about."""
    for p in sorted(batch_dir.iterdir()):
        name = p.name
        if name.startswith(".") or name in (BATCH_FILE, *forms(TRIALS_FILE)):
            continue
        if p.is_dir():
            warn(p, "sub-folder ignored")
            continue
        if name.endswith(TDMS_INDEX) and p.with_suffix(TDMS).exists():
            continue  # NI's index of the TDMS file beside it: npTDMS reads the file itself
        for suffix in STREAM_SUFFIXES:
            if name.endswith(suffix):
                tid = name[: -len(suffix)]
                if tid not in listed:
                    probs.add(
                        str(p), f"no row for trial {tid!r} in {TRIALS_FILE}: file not ingested", trial_id=tid
                    )
                break
        else:
            warn(p, "not a rig-log/1 file; ignored")
