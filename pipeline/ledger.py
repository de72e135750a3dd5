"""One record of every trial of every batch: where it was used, or at which stage, where and why it
was set aside.

Each stage keeps its own record, in its own outputs: ingest the batches it read and every located
problem (`reports/ingest/batches.json`, `quarantine.json`), resample one row per trial
(`reports/resample/offsets.csv`), split the place of every trial (`data/processed/manifest.json`),
calibrate the trials each unit's calibration used or set aside (`data/calibration/<unit>.json`).
`build` reads them in pipeline order, so a trial's entry is the last decision made about it: set
aside at the first stage that refused it, otherwise used in the split (or calibration) split gave
it. Pure: the ledger stage and the tests call it with those records as data.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

from needlecue_runtime.vocab import angle_name

FORMAT = "needlecue-ledger/1"
USED, SET_ASIDE = "used", "set aside"
STAGES = ("ingest", "resample", "split", "calibrate")
RESAMPLE_ASIDE = "set aside: "  # the prefix of a set-aside trial's status in offsets.csv


@dataclass(frozen=True)
class Where:
    """One located reason: the file (a trial's files when no single one is to blame), and the line
    and column where the reader found it."""

    file: str
    reason: str
    line: int | None = None
    column: str | None = None


@dataclass(frozen=True)
class Entry:
    """A trial's place (`trial_id` None: a batch whose trials could not be listed)."""

    batch_id: str
    trial_id: str | None
    source: str  # the batch folder it was read from
    outcome: str  # USED | SET_ASIDE
    stage: str  # the stage that decided
    angle: str | None = None
    use: str | None = None  # train | val | test | external | calibration (USED only)
    unit_id: str | None = None  # calibration trials: the unit they calibrate
    note: str | None = None
    flag: str | None = None  # USED only: kept, but looked at (resample's flag: a low alignment quality)
    unused_axes: tuple[str, ...] | None = None  # USED only: forces its reference records that its angle's
    # models do not estimate (not every batch at the angle records them: pipeline.dataset.split)
    where: tuple[Where, ...] = field(default_factory=tuple)


Key = tuple[str, str]  # (batch_id, trial_id)


@dataclass(frozen=True)
class _Later:
    """What the stages after ingest decided, by trial."""

    resampled: dict[Key, Mapping[str, Any]]  # offsets.csv rows
    split_aside: dict[Key, Mapping[str, Any]]
    placed: dict[Key, tuple[str, str]]  # (angle, split)
    calibrating: dict[Key, str]  # unit
    calibrated: set[Key]  # in some unit's calibration document
    calibrate_aside: dict[Key, Mapping[str, Any]]
    left_out: dict[tuple[str, str], list[str]] = field(default_factory=dict)  # (batch, angle): axes unused


def _where(problem: Mapping[str, Any]) -> Where:
    return Where(str(problem["file"]), str(problem["reason"]), problem.get("line"), problem.get("column"))


def _trial_files(source: str, trial_id: str) -> str:
    return f"{source}/{trial_id}.*"


def build(
    batches: Sequence[Mapping[str, Any]],
    quarantine: Sequence[Mapping[str, Any]],
    offsets: Sequence[Mapping[str, Any]],
    manifest: Mapping[str, Any],
    calibrations: Sequence[Mapping[str, Any]],
    trained: Iterable[float],
) -> list[Entry]:
    """Every trial's entry, sorted by (batch, trial). `batches` is ingest's `batches.json`, `quarantine`
    its problems, `offsets` resample's rows, `manifest` split's, `calibrations` the unit documents,
    `trained` params.yaml `train.angles`."""
    trained_names = {angle_name(a) for a in trained}
    resampled = {(str(r["batch_id"]), str(r["trial_id"])): r for r in offsets}
    placed: dict[Key, tuple[str, str]] = {}
    for angle, entry in manifest.get("angles", {}).items():
        for split, trials in entry.get("splits", {}).items():
            for t in trials:
                placed[(t["batch_id"], t["trial_id"])] = (angle, split)
    split_aside = {(s["batch_id"], s["trial_id"]): s for s in manifest.get("set_aside", [])}
    calibrating = {
        (t["batch_id"], t["trial_id"]): t["unit_id"]
        for trials in manifest.get("calibration", {}).values()
        for t in trials
    }
    calibrated = {(t["batch_id"], t["trial_id"]) for doc in calibrations for t in doc.get("trials", [])}
    calibrate_aside: dict[Key, Mapping[str, Any]] = {}
    for doc in calibrations:
        for s in doc.get("set_aside", []):
            calibrate_aside[(s["batch_id"], s["trial_id"])] = s
    left_out: dict[tuple[str, str], list[str]] = {}  # split's axes_left_out, of angles and calibration
    for angle, entry in manifest.get("angles", {}).items():
        left_out |= {(batch, angle): list(axes) for batch, axes in entry.get("axes_left_out", {}).items()}
    for angle, by_batch in manifest.get("calibration_axes_left_out", {}).items():
        left_out |= {(batch, angle): list(axes) for batch, axes in by_batch.items()}
    later = _Later(resampled, split_aside, placed, calibrating, calibrated, calibrate_aside, left_out)

    out: list[Entry] = []
    attached: set[int] = set()  # the quarantine's problems some entry carries

    def located(batch_id: str, trial: str | None, source: str) -> list[int]:
        return [
            i
            for i, q in enumerate(quarantine)
            if q["batch_id"] == batch_id and q.get("trial_id") == trial and _inside(q, source)
        ]

    def entry(batch_id: str, trial: str | None, source: str, problems: list[int]) -> Entry:
        attached.update(problems)
        where = tuple(_where(quarantine[i]) for i in problems)
        return Entry(batch_id, trial, source, SET_ASIDE, "ingest", where=where)

    for b in batches:
        batch_id, source = str(b["batch_id"]), str(b["source_dir"])
        batch_level = located(batch_id, None, source)
        accepted = list(b.get("trials_accepted", [])) if b.get("accepted") else []
        trials = sorted({*b.get("trials_accepted", []), *b.get("trials_set_aside", [])})
        if not trials:  # none could be listed: the batch as a whole
            out.append(entry(batch_id, None, source, batch_level))
        for trial in trials:
            if trial in accepted:
                out.append(_after_ingest((batch_id, trial), source, later, trained_names))
            else:
                out.append(entry(batch_id, trial, source, located(batch_id, trial, source) + batch_level))
    for i, q in enumerate(quarantine):  # a problem no listed trial carries (a stray stream file): kept
        if i not in attached:
            trial = q.get("trial_id")
            out.append(
                Entry(str(q["batch_id"]), trial, str(q["file"]), SET_ASIDE, "ingest", where=(_where(q),))
            )
    return sorted(out, key=lambda e: (e.batch_id, e.trial_id or "", e.source))


def _inside(problem: Mapping[str, Any], source: str) -> bool:
    """Whether a problem's file is the batch folder `source` or lies in it (two copies of a batch
    share its id, not their folder)."""
    file = str(problem["file"])
    return file == source or file.startswith(source.rstrip("/") + "/")


def _after_ingest(key: Key, source: str, later: _Later, trained: set[str]) -> Entry:
    """The entry of a trial ingest accepted: the first later stage that set it aside, or its use."""
    batch_id, trial = key
    files = _trial_files(source, trial)
    row = later.resampled.get(key)
    angle = angle_name(float(row["angle_deg"])) if row and row.get("angle_deg") not in (None, "") else None
    if row is None:
        reason = "accepted by ingest, but resample has no row for it"
        return Entry(batch_id, trial, source, SET_ASIDE, "resample", angle, where=(Where(files, reason),))
    status = str(row["status"])
    if status != "ok":
        reason = status.removeprefix(RESAMPLE_ASIDE)
        return Entry(batch_id, trial, source, SET_ASIDE, "resample", angle, where=(Where(files, reason),))
    flag = str(row.get("flag") or "") or None
    if key in later.split_aside:
        reason = str(later.split_aside[key]["reason"])
        return Entry(batch_id, trial, source, SET_ASIDE, "split", angle, where=(Where(files, reason),))
    if key in later.calibrating:
        unit = later.calibrating[key]
        if key in later.calibrated:
            unused = later.left_out.get((batch_id, angle or ""))
            return Entry(
                batch_id,
                trial,
                source,
                USED,
                "calibrate",
                angle,
                "calibration",
                unit,
                note=_unused_note(unused, angle),
                flag=flag,
                unused_axes=tuple(unused) if unused else None,
            )
        s = later.calibrate_aside.get(key)
        reason = str(s["reason"]) if s else "split gave it to calibration, but no unit calibration used it"
        file = str(s["file"]) if s else files
        return Entry(
            batch_id, trial, source, SET_ASIDE, "calibrate", angle, unit_id=unit, where=(Where(file, reason),)
        )
    if key in later.placed:
        at, split = later.placed[key]
        notes = []
        if at not in trained:
            notes.append(
                f"no model is trained at {at}° (train.angles): only other angles' models are scored on it"
            )
        unused = later.left_out.get((batch_id, at))
        if unused:
            notes.append(_unused_note(unused, at))
        note = "; ".join(notes) or None
        return Entry(
            batch_id,
            trial,
            source,
            USED,
            "split",
            at,
            split,
            note=note,
            flag=flag,
            unused_axes=tuple(unused) if unused else None,
        )
    reason = "resampled, but split placed it nowhere"
    return Entry(batch_id, trial, source, SET_ASIDE, "split", angle, where=(Where(files, reason),))


def _unused_note(axes: Sequence[str] | None, angle: str | None) -> str | None:
    """The note on a used trial whose batch records force `axes` its angle's models do not estimate."""
    if not axes:
        return None
    return (
        f"its reference's {', '.join(axes)} not used: the models at {angle}° do not estimate them (not "
        "every batch there records them)"
    )


def counts(entries: Sequence[Entry]) -> dict[str, Any]:
    """Trials used (per use) and set aside (per stage); batch-level entries counted apart."""
    trials = [e for e in entries if e.trial_id is not None]
    used: dict[str, int] = {}
    aside = dict.fromkeys(STAGES, 0)
    for e in trials:
        if e.outcome == USED:
            used[e.use or "-"] = used.get(e.use or "-", 0) + 1
        else:
            aside[e.stage] = aside.get(e.stage, 0) + 1
    return {
        "trials": len(trials),
        "used": sum(used.values()),
        "used_by_split": dict(sorted(used.items())),
        "set_aside": sum(aside.values()),
        "flagged": sum(1 for e in trials if e.flag),
        "set_aside_by_stage": aside,
        "batches_set_aside_whole": sorted(
            {f"{e.batch_id} ({e.source})" for e in entries if e.trial_id is None}
        ),
    }


def document(entries: Sequence[Entry]) -> dict[str, Any]:
    """The ledger as written to `reports/ledger.json`."""
    return {"format": FORMAT, "counts": counts(entries), "entries": [_plain(e) for e in entries]}


def _plain(e: Entry) -> dict[str, Any]:
    d = asdict(e)
    d["where"] = [{k: v for k, v in w.items() if v is not None} for w in d["where"]]
    return {k: v for k, v in d.items() if v is not None and v != []}


def of_batches(doc: Mapping[str, Any], batch_ids: Iterable[str]) -> list[dict[str, Any]]:
    """The entries of these batches in a written ledger."""
    wanted = set(batch_ids)
    return [e for e in doc.get("entries", []) if e["batch_id"] in wanted]
