"""`needlecue retrain`: follow new tissue batches without a person in the loop (cron, systemd, CI).

One run: take the lock; find the batches under `data.raw_dir` that are new or changed since the
last ingest; check them (a bad batch is reported and set aside by the pipeline, the rest goes on);
`dvc repro` (only what the new data touches reruns; `register` registers and promotes by the
champion rule); write a retrain report. Nothing new: nothing runs, nothing is registered.

Exit codes (also in docs/retraining.md):
  0  nothing new: nothing ran, nothing was registered
  1  failed: `dvc repro` or a check failed; the report says where. The registry changes only in
     the last stage, so a failure before it leaves every alias as it was (one inside `register`
     keeps the decisions made for the angles before it); the next run resumes.
  2  retrained: new models trained, tracked and registered (champions moved only where better)
  3  retrained, but some trial of a new or changed batch was set aside, at whichever stage (the
     report lists every new trial's place, from the ledger stage's reports/ledger/ledger.json)
  4  busy: another retrain (or a DVC command) holds the project; this one did nothing

A run killed half way leaves `data/raw` untouched (the pipeline never writes there), the
registry as it was unless `register` had started (it is idempotent and finishes an interrupted
decision next time), and DVC's outputs consistent with `dvc.lock` stage by stage, so the next
run picks up where it stopped, and reports the batches the killed run took (`UNFINISHED`). The lock
is an OS file lock: it dies with its process.
"""

from __future__ import annotations

import datetime as dt
import fcntl
import json
import logging
import os
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from pipeline.config import DataParams, IngestParams, load_section
from pipeline.execution.dvc_api import Busy, dvc_changed, dvc_repro
from pipeline.ledger import USED, of_batches
from pipeline.logs import Log
from pipeline.metrics.document import EVALUATION_FILE, Evaluation, read_evaluation
from pipeline.reporting.ledger import entry_text

EXIT_NOTHING, EXIT_FAILED, EXIT_RETRAINED, EXIT_SET_ASIDE, EXIT_BUSY = 0, 1, 2, 3, 4
LOCK_FILE = Path(".dvc/tmp/needlecue-retrain.lock")
INGESTED = Path("data/interim/ingested")
REPORT_DIR = Path("reports/retrain")
# the batches a run took, until its `dvc repro` succeeds: a run killed after ingest took them still
# has them reported (and set aside ones still counted) by the run that finishes its job
UNFINISHED = REPORT_DIR / "unfinished.json"
LEDGER = Path("reports/ledger/ledger.json")  # the ledger stage's output (dvc.yaml)
MAX_LISTED = 50  # trials listed per batch in the report; the ledger has them all
logger = logging.getLogger(__name__)


@contextmanager
def lock(path: Path) -> Iterator[None]:
    """An exclusive, non-blocking OS lock on `path` (released when the process ends, even killed).
    Raises `Busy` naming the holder when another process has it."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = Path(path).read_text().strip() or "unknown process"
            raise Busy(f"another retrain is running ({holder}; lock {path}): nothing done") from None
        os.ftruncate(fd, 0)
        os.write(fd, f"pid {os.getpid()}, started {_now()}".encode())
        yield
    finally:
        os.close(fd)  # closing releases the lock


def _now() -> str:
    return dt.datetime.now(dt.UTC).strftime("%Y-%m-%dT%H:%M:%SZ")


@dataclass(frozen=True)
class Pending:
    """A batch folder the last ingest has not seen in this form."""

    batch_id: str
    path: str
    status: str  # "new" | "changed"
    problems: list[str] = field(default_factory=list)  # from the check, before the pipeline runs


def pending_batches(
    raw_dir: Path, ingested: Path, params: IngestParams, stage_raw_dir: Path | None = None
) -> list[Pending]:
    """New or changed batch folders of `raw_dir`, by the ingest stage's own fingerprints;
    `stage_raw_dir` is `raw_dir` as the stage names it (`data.raw_dir`, relative to the project)."""
    from pipeline.rig.batch_store import FINGERPRINT
    from pipeline.rig.fingerprint import fingerprint
    from pipeline.rig.format import batch_dirs

    out = []
    for batch in batch_dirs(raw_dir):
        stored = ingested / batch.name / FINGERPRINT
        if not stored.is_file():
            out.append(Pending(batch.name, str(batch), "new"))
            continue
        try:
            known = json.loads(stored.read_text()).get("fingerprint")
        except (OSError, ValueError):
            known = None
        name = str((stage_raw_dir or raw_dir) / batch.name)
        if known != fingerprint(batch, params, source_dir=name)["fingerprint"]:
            out.append(Pending(batch.name, str(batch), "changed"))
    return out


def with_unfinished(pending: list[Pending], root: Path) -> list[Pending]:
    """`pending` and, after them, the batches of a run whose `dvc repro` did not finish (`UNFINISHED`)
    that are not among them and are still there: its ingest may have taken them, so they no longer
    differ from the ingest cache, but no report has said what became of them yet."""
    path = root / UNFINISHED
    if not path.is_file():
        return pending
    try:
        left = [Pending(**entry) for entry in json.loads(path.read_text())]
    except (OSError, ValueError, TypeError) as e:
        logger.warning("ignoring %s: %s", path, e)
        return pending
    known = {p.batch_id for p in pending}
    return pending + [p for p in left if p.batch_id not in known and Path(p.path).exists()]


def check_pending(pending: list[Pending], params: IngestParams) -> list[Pending]:
    """Each pending batch with the problems `needlecue check` finds in it (empty: fine)."""
    from pipeline.rig.check import check_folders

    return [
        Pending(p.batch_id, p.path, p.status, [str(x) for x in check_folders([Path(p.path)], params)])
        for p in pending
    ]


def _read_json(path: Path) -> dict[str, Any]:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return {}


def _read_evaluation(path: Path) -> Evaluation | None:
    """evaluation.json, or None where there is none yet or this needlecue cannot read it (then the
    report has no figures to compare, rather than failing the retrain)."""
    try:
        return read_evaluation(path)
    except (OSError, ValueError):
        return None


def _mean_nrmse(evaluation: Evaluation | None) -> dict[str, dict[str, float]]:
    """{angle: {model: external NRMSE, mean of axes}} from evaluation.json's within_angle."""
    out: dict[str, dict[str, float]] = {}
    for model, angles in ({} if evaluation is None else evaluation.within_angle).items():
        for angle, axes in angles.items():
            values = [a.nrmse_pct for a in axes.values() if a.nrmse_pct is not None]
            if values:
                out.setdefault(angle, {})[model] = round(sum(values) / len(values), 4)
    return out


def summarise(
    pending: list[Pending],
    ran: list[str],
    before: Evaluation | None,
    after: Evaluation | None,
    registry: dict[str, Any],
    ledger: dict[str, Any],
) -> dict[str, Any]:
    """The retrain report's content (pure: tests call it directly). `ledger` is the ledger stage's
    `ledger.json`: every trial of the new batches, used where or set aside at which stage and why."""
    retrained = sorted(
        {s.split("@", 1)[1].split("-", 1)[0] for s in ran if s.startswith("train@")}, key=float
    )
    nrmse_before, nrmse_after = _mean_nrmse(before), _mean_nrmse(after)
    entries = of_batches(ledger, [p.batch_id for p in pending])
    used = {e["batch_id"] for e in entries if e["outcome"] == USED}
    # nothing of the batch was used, or the ledger does not know it (then nobody can say it was)
    set_aside = sorted({p.batch_id for p in pending} - used)
    trials_set_aside = [e for e in entries if e["outcome"] != USED and e.get("trial_id")]
    registered = registry.get("angles", {}) if "register" in ran else {}
    return {
        "batches": [asdict(p) for p in pending],
        "batches_set_aside": set_aside,
        "trials_set_aside": trials_set_aside,
        "trials": entries,
        "stages_run": ran,
        "angles_retrained": retrained,
        "metrics": {
            a: {"before": nrmse_before.get(a, {}), "after": nrmse_after.get(a, {})} for a in retrained
        },
        "registered": {a: e for a, e in registered.items() if e.get("action") == "registered"},
        "promoted": [
            a for a, e in registered.items() if e.get("action") == "registered" and "champion" in e["aliases"]
        ],
    }


def outcome(repro_code: int, report: dict[str, Any]) -> tuple[int, str]:
    """(exit code, outcome) of a retrain whose `dvc repro` exited `repro_code`: set aside (3) as soon
    as one trial of a new or changed batch was set aside at any stage."""
    if repro_code != 0:
        return EXIT_FAILED, "failed"
    if report["batches_set_aside"] or report["trials_set_aside"]:
        return EXIT_SET_ASIDE, "retrained, some new data set aside"
    return EXIT_RETRAINED, "retrained"


EMPTY_REPORT: dict[str, Any] = {
    "batches": [],
    "batches_set_aside": [],
    "trials_set_aside": [],
    "trials": [],
    "stages_run": [],
    "angles_retrained": [],
    "metrics": {},
    "registered": {},
    "promoted": [],
}


def _pct(x: float | None) -> str:
    return "—" if x is None else f"{x:.2f}"


def render(report: dict[str, Any]) -> str:
    """The retrain report as Markdown."""
    lines = [
        f"# Retrain {report['started']}",
        "",
        f"Outcome: **{report['outcome']}** (exit {report['exit_code']})",
        "",
    ]
    if report.get("error"):
        lines += ["```", report["error"], "```", ""]
    lines += ["## New or changed batches", ""]
    if not report["batches"]:
        lines.append("None.")
    for b in report["batches"]:
        status = "set aside" if b["batch_id"] in report["batches_set_aside"] else "used"
        lines.append(f"- `{b['batch_id']}` ({b['status']}, {status}): {b['path']}")
        mine = [e for e in report.get("trials", []) if e["batch_id"] == b["batch_id"]]
        for e in mine[:MAX_LISTED]:  # every trial's place, from the ledger
            lines.append(f"  - `{e.get('trial_id') or '(whole batch)'}`: {entry_text(e)}")
        if len(mine) > MAX_LISTED:
            lines.append(f"  - ... and {len(mine) - MAX_LISTED} more: `reports/ledger/ledger.md`")
        if not mine:  # no ledger for it (the pipeline failed first): what the check before the run found
            lines += [f"  - {p}" for p in b["problems"][:20]]
    if report["trials_set_aside"]:
        n = len(report["trials_set_aside"])
        lines += ["", f"{n} new trial(s) set aside: see above and `reports/ledger/ledger.md`."]
    lines += ["", "## Angles retrained", ""]
    if not report["angles_retrained"]:
        lines.append("None.")
    else:
        lines += ["| angle | model | external NRMSE before (%) | after (%) |", "|---|---|---|---|"]
        for angle in report["angles_retrained"]:
            m = report["metrics"][angle]
            for model in sorted(set(m["before"]) | set(m["after"])):
                b, a = (_pct(m[when].get(model)) for when in ("before", "after"))
                lines.append(f"| {angle}° | {model} | {b} | {a} |")
    lines += ["", "## Registry", ""]
    if not report["registered"]:
        lines.append("Nothing registered.")
    for e in report["registered"].values():
        aliases = ", ".join(e["aliases"])
        lines.append(f"- `{e['model']}` v{e['version']} ({e['kind']}) → {aliases}: {e.get('reason', '')}")
    lines += ["", f"Stages run: {', '.join(report['stages_run']) or 'none'}.", ""]
    return "\n".join(lines)


def write_report(root: Path, report: dict[str, Any]) -> Path:
    """reports/retrain/<started>.{json,md} and latest.{json,md}; returns the .md path."""
    folder = root / REPORT_DIR
    folder.mkdir(parents=True, exist_ok=True)
    stamp = report["started"].replace(":", "").replace("-", "")
    md, js = render(report), json.dumps(report, indent=2, sort_keys=True) + "\n"
    for name in (stamp, "latest"):
        (folder / f"{name}.md").write_text(md)
        (folder / f"{name}.json").write_text(js)
    return folder / f"{stamp}.md"


def retrain(
    root: Path, params_path: Path = Path("params.yaml"), log: Log = logger.info
) -> tuple[int, dict[str, Any]]:
    """One retrain of the project at `root`: (exit code, report). See the module docstring."""
    started = _now()
    try:
        with lock(root / LOCK_FILE):
            try:
                return _retrain_locked(root, params_path, started, log)
            except Busy:
                raise
            except Exception as e:  # a failure before or around `dvc repro`: still leave a report
                report = {**EMPTY_REPORT, "started": started, "outcome": "failed", "exit_code": EXIT_FAILED}
                report["error"] = f"{type(e).__name__}: {e}"
                log(f"failed: {report['error']}; report {write_report(root, report)}")
                return EXIT_FAILED, report
    except Busy as e:
        log(str(e))
        return EXIT_BUSY, {"started": started, "outcome": "busy", "exit_code": EXIT_BUSY, "error": str(e)}


def _retrain_locked(root: Path, params_path: Path, started: str, log: Log) -> tuple[int, dict[str, Any]]:
    t0 = time.perf_counter()
    params_file = root / params_path
    stage_raw_dir = load_section(DataParams, "data", params_file).raw_dir
    raw_dir = root / stage_raw_dir
    ingest_params = load_section(IngestParams, "ingest", params_file)
    pending = with_unfinished(pending_batches(raw_dir, root / INGESTED, ingest_params, stage_raw_dir), root)
    changed = dvc_changed(root, log)
    if not changed:  # DVC decides: a batch "changed" only for the ingest cache (a library upgrade) is not new
        if pending:
            log(
                f"{len(pending)} batch(es) differ from the ingest cache's fingerprints but DVC has nothing "
                "to rerun (their bytes are the same; code or library versions changed?)"
            )
        log(f"nothing new in {raw_dir} and every stage is up to date: nothing to do")
        return EXIT_NOTHING, {"started": started, "outcome": "nothing new", "exit_code": EXIT_NOTHING}
    log(f"{len(pending)} new or changed batch(es): {', '.join(p.batch_id for p in pending) or 'none'}")
    pending = check_pending(pending, ingest_params)
    for p in pending:
        state = (
            f"{len(p.problems)} problem(s), the pipeline will set aside what they touch"
            if p.problems
            else "ok"
        )
        log(f"checked {p.batch_id} ({p.status}): {state}")
        for problem in p.problems[:5]:
            log(f"    {problem}")
    before = _read_evaluation(root / "reports" / EVALUATION_FILE)
    log(f"dvc repro ({len(changed)} stage(s) out of date)")
    taken = [{"batch_id": p.batch_id, "path": p.path, "status": p.status} for p in pending]
    (root / UNFINISHED).parent.mkdir(parents=True, exist_ok=True)
    (root / UNFINISHED).write_text(json.dumps(taken, indent=2) + "\n")
    code, ran, tail = dvc_repro(root, log)
    if code == 0:
        (root / UNFINISHED).unlink()
    report = summarise(
        pending,
        ran,
        before,
        _read_evaluation(root / "reports" / EVALUATION_FILE),
        _read_json(root / "reports" / "registry.json"),
        _read_json(root / LEDGER),
    )
    report["started"] = started
    report["seconds"] = round(time.perf_counter() - t0, 1)
    exit_code, report["outcome"] = outcome(code, report)
    report["exit_code"] = exit_code
    if code != 0:
        report["error"] = "\n".join(tail)
    path = write_report(root, report)
    log(
        f"{report['outcome']} in {report['seconds']:.0f} s: angles {report['angles_retrained'] or 'none'}, "
        f"promoted {report['promoted'] or 'none'}; report {path}"
    )
    return exit_code, report
