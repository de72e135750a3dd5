"""The ingest stage's reports, rewritten each run in REPORT_DIR: ``quarantine.json`` (every
Problem), ``batches.json`` (every batch folder read: its trials accepted and set aside, which the
ledger stage starts from), ``summary.md``, ``gx/<batch_id>.json`` and GX Data Docs under
``data_docs/index.html``.
"""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

from pipeline.rig.batch_store import write_json
from pipeline.rig.datadocs import write_data_docs
from pipeline.rig.ingest import IngestResult


def summary_md(result: IngestResult) -> str:
    """summary.md: counts, every batch's outcome, every Problem and warning."""
    acc = [b for b in result.batches if b.accepted]
    lines = [
        "# Ingest summary",
        "",
        "| | batches | trials |",
        "|---|---:|---:|",
        f"| accepted | {len(acc)} | {sum(len(b.trials_accepted) for b in acc)} |",
        f"| set aside | {len(result.batches) - len(acc)} | "
        f"{sum(len(b.trials_set_aside) for b in result.batches)} |",
        "",
        "## Batches",
        "",
    ]
    for b in result.batches:
        state = (
            f"accepted: {len(b.trials_accepted)} trials, {len(b.trials_set_aside)} set aside"
            if b.accepted
            else "**set aside**"
        )
        # whether a batch was parsed now or reused from the cache goes to the log, not here: the
        # summary is a stage output, the same bytes whatever the cache held (docs/reproducibility.md)
        dup = ", duplicate" if b.action == "duplicate" else ""
        lines.append(f"- `{b.batch_id}` ({b.source_dir}{dup}): {state}")
    problems = result.problems
    lines += ["", f"## Problems ({len(problems)})", ""]
    lines += [f"- {p}" for p in problems] or ["None."]
    warnings = [w for b in result.batches for w in b.warnings]
    if warnings:
        lines += ["", f"## Warnings ({len(warnings)})", ""] + [f"- {w}" for w in warnings]
    if result.removed:
        lines += ["", "## Removed from the ingest output", ""] + [f"- {r}" for r in result.removed]
    lines += [
        "",
        "Details: `quarantine.json`, `gx/<batch_id>.json`, Data Docs in `data_docs/index.html`.",
        "",
    ]
    return "\n".join(lines)


def batches_record(result: IngestResult) -> list[dict[str, Any]]:
    """batches.json: every batch folder read (a second copy of a batch id too), with its trials."""
    return [
        {
            "batch_id": b.batch_id,
            "source_dir": str(b.source_dir),
            "accepted": b.accepted,
            "duplicate": b.action == "duplicate",
            "trials_accepted": list(b.trials_accepted),
            "trials_set_aside": list(b.trials_set_aside),
        }
        for b in result.batches
    ]


def write_reports(result: IngestResult, report_dir: Path, *, data_docs: bool = True) -> None:
    """quarantine.json, batches.json, summary.md, gx/<batch_id>.json and GX Data Docs (all rewritten)."""
    report_dir.mkdir(parents=True, exist_ok=True)
    for sub in ("gx", "data_docs"):
        if (report_dir / sub).exists():
            shutil.rmtree(report_dir / sub)
    quarantine = [
        {
            "batch_id": p.batch_id,
            "trial_id": p.trial_id,
            "file": p.file,
            "line": p.line,
            "column": p.column,
            "reason": p.reason,
        }
        for p in result.problems
    ]
    write_json(quarantine, report_dir / "quarantine.json")
    write_json(batches_record(result), report_dir / "batches.json")
    (report_dir / "summary.md").write_text(summary_md(result))
    gx_dir = report_dir / "gx"
    gx_dir.mkdir()
    results = {b.batch_id: b.gx for b in result.batches if b.gx and b.action != "duplicate"}
    for batch_id, res in results.items():
        write_json(res, gx_dir / f"{batch_id}.json")
    if data_docs:
        write_data_docs(results, report_dir / "data_docs")
