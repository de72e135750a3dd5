"""`ledger.md`: the ledger (`pipeline.ledger`) for people: the counts, the trials used per angle and
split, and every trial set aside with its stage, place and reason."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from needlecue_runtime.vocab import sorted_angles

SPLIT_ORDER = ("train", "val", "test", "external", "calibration")


def where_text(where: Mapping[str, Any]) -> str:
    """`file:line (column): reason`, with what is known of the place."""
    place = str(where["file"])
    if where.get("line") is not None:
        place += f":{where['line']}"
    if where.get("column"):
        place += f" ({where['column']})"
    return f"{place}: {where['reason']}"


def entry_text(e: Mapping[str, Any]) -> str:
    """One line for a trial's place: `used: train at 15°` or `set aside at resample: ...`."""
    if e["outcome"] == "used":
        text = f"used: {e['use']} at {e['angle']}°"
        if e.get("unit_id"):
            text += f" (unit {e['unit_id']})"
        return text + (f"; {e['note']}" if e.get("note") else "")
    reasons = "; ".join(where_text(w) for w in e.get("where", [])) or "no reason recorded"
    return f"set aside at {e['stage']}: {reasons}"


def markdown(doc: Mapping[str, Any]) -> str:
    """The whole ledger as Markdown."""
    c = doc["counts"]
    entries = doc["entries"]
    lines = [
        "# Ledger: every trial of every batch",
        "",
        f"{c['trials']} trials: **{c['used']} used**, **{c['set_aside']} set aside** "
        f"({', '.join(f'{s}: {n}' for s, n in c['set_aside_by_stage'].items())}).",
    ]
    if c["batches_set_aside_whole"]:
        whole = ", ".join(c["batches_set_aside_whole"])
        lines.append(f"Batches set aside before their trials could be listed: {whole}.")
    used = [e for e in entries if e["outcome"] == "used"]
    table: dict[str, dict[str, int]] = {}
    for e in used:
        row = table.setdefault(e["angle"], {})
        row[e["use"]] = row.get(e["use"], 0) + 1
    lines += ["", "## Used, per angle", "", "| angle | " + " | ".join(SPLIT_ORDER) + " |"]
    lines.append("|---:|" + "---:|" * len(SPLIT_ORDER))
    for angle in sorted_angles(table):
        lines.append(f"| {angle}° | " + " | ".join(str(table[angle].get(s, 0)) for s in SPLIT_ORDER) + " |")
    notes = sorted({e["note"] for e in used if e.get("note")})
    lines += [f"- {n}" for n in notes]
    flagged = [e for e in used if e.get("flag")]
    if flagged:
        lines += ["", f"## Used, flagged ({len(flagged)})", ""]
        lines += [f"- `{e['batch_id']}/{e['trial_id']}`: {e['flag']}" for e in flagged]
    aside = [e for e in entries if e["outcome"] != "used"]
    lines += ["", f"## Set aside ({len(aside)})", ""]
    if not aside:
        lines.append("None.")
    for e in aside:
        name = f"{e['batch_id']}/{e['trial_id']}" if e.get("trial_id") else f"{e['batch_id']} (whole batch)"
        lines.append(f"- `{name}` ({e['source']}): {entry_text(e)}")
    lines += ["", "Machine-readable: `ledger.json` (`needlecue-ledger/1`).", ""]
    return "\n".join(lines)
