"""Reading one batch's `batch.yaml`: parsed, checked against the `BatchMeta` model, and every
error placed on its line (`docs/rig-log-format.md`, section `batch.yaml`).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import yaml
from pydantic import ValidationError

from needlecue_runtime.frontend import CIRCUITS
from needlecue_runtime.vocab import NON_CHANNELS
from pipeline.rig.csvfile import encoding_hint
from pipeline.rig.format import BATCH_FILE, ID_PATTERN, BatchMeta, is_valid_id
from pipeline.rig.problems import ProblemLog

# Columns the pipeline adds: the validated frames' own (pipeline.rig.reader) and the processed
# frames' (ids, time, phase, the reference force). A channel of the same name would be ambiguous.
RESERVED = frozenset({"trial_id", "line", "dt", *NON_CHANNELS})
MAX_BYTES = 1 << 20  # a batch.yaml is a page of metadata; anything near this is not one
MAX_NODES = 10_000  # YAML nodes after alias expansion (a real batch.yaml has about a hundred)


def _alias_problem(root: yaml.Node | None) -> tuple[str, int] | None:
    """(what, line) if aliases make the document recursive or expand it beyond MAX_NODES nodes (an
    alias bomb): safe_load would recurse without end or build it for minutes. Walks the composed tree
    as its aliases expand, so it stops after MAX_NODES steps whatever the document."""
    if root is None:
        return None
    visited = 0
    stack: list[tuple[yaml.Node, frozenset[int]]] = [(root, frozenset())]
    while stack:
        node, path = stack.pop()
        visited += 1
        if visited > MAX_NODES:
            return (
                f"aliases expand the document beyond {MAX_NODES} nodes (a YAML alias bomb?)",
                node.start_mark.line + 1,
            )
        if id(node) in path:
            return "a recursive alias: this node contains itself", node.start_mark.line + 1
        inner = path | {id(node)}
        if isinstance(node, yaml.MappingNode):
            stack.extend((child, inner) for pair in reversed(node.value) for child in reversed(pair))
        elif isinstance(node, yaml.SequenceNode):
            stack.extend((child, inner) for child in reversed(node.value))
    return None


def _yaml_line(node: yaml.Node | None, loc: Sequence[Any]) -> int | None:
    """1-based line of the deepest node of `loc` (a pydantic error location) in a composed YAML tree."""
    if node is None:
        return None
    found = node
    for part in loc:
        nxt = None
        if isinstance(found, yaml.MappingNode):
            nxt = next((v for k, v in found.value if getattr(k, "value", None) == str(part)), None)
        elif isinstance(found, yaml.SequenceNode) and isinstance(part, int) and part < len(found.value):
            nxt = found.value[part]
        if nxt is None:
            break
        found = nxt
    return found.start_mark.line + 1


def _duplicate_key(node: yaml.Node | None) -> tuple[str, int] | None:
    """First key that appears twice in one mapping (safe_load would silently keep the last)."""
    if isinstance(node, yaml.MappingNode):
        seen: set[str] = set()
        for k, v in node.value:
            key = getattr(k, "value", None)
            if isinstance(key, str):
                if key in seen:
                    return key, k.start_mark.line + 1
                seen.add(key)
            if found := _duplicate_key(v):
                return found
    elif isinstance(node, yaml.SequenceNode):
        for v in node.value:
            if found := _duplicate_key(v):
                return found
    return None


NOT_PLAIN = {  # YAML types that JSON (and so every record the stages write) has no word for
    "tag:yaml.org,2002:binary": "binary data (!!binary)",
    "tag:yaml.org,2002:set": "a set (!!set)",
    "tag:yaml.org,2002:omap": "an ordered map (!!omap)",
    "tag:yaml.org,2002:pairs": "a list of pairs (!!pairs)",
}


def _not_plain(root: yaml.Node | None) -> tuple[str, int] | None:
    """(what, line) of the first value that is not a plain value (text, number, true/false, null, a
    date, a list or a mapping of those): binary data, a set, a non-finite number. batch.yaml is
    copied into JSON records, and a set would make the channel order depend on the hash seed."""
    stack = [root] if root is not None else []
    while stack:
        node = stack.pop()
        line = node.start_mark.line + 1
        if node.tag in NOT_PLAIN:
            return f"{NOT_PLAIN[node.tag]}: batch.yaml holds plain values only", line
        if node.tag == "tag:yaml.org,2002:float" and str(node.value).lower().lstrip("+-") in (".inf", ".nan"):
            return f"{node.value} is not a finite number", line
        if isinstance(node, yaml.MappingNode):
            stack.extend(child for pair in reversed(node.value) for child in reversed(pair))
        elif isinstance(node, yaml.SequenceNode):
            stack.extend(reversed(node.value))
    return None


def _without_tags(loc: tuple[Any, ...]) -> tuple[Any, ...]:
    """A pydantic error location without the tag a tagged union puts after its field
    (`sensor.front_end.divider.fixed_kohm` -> `sensor.front_end.fixed_kohm`): the key as written."""
    return tuple(
        part for i, part in enumerate(loc) if not (i and loc[i - 1] == "front_end" and part in CIRCUITS)
    )


def read_meta(batch_dir: Path, probs: ProblemLog) -> BatchMeta | None:
    """batch.yaml parsed and validated; None (with Problems) if the batch must be set aside."""
    path = batch_dir / BATCH_FILE
    file = str(path)
    if not path.is_file():
        probs.add(file, f"missing {BATCH_FILE}" if not path.exists() else "not a regular file")
        return None
    try:
        if path.stat().st_size > MAX_BYTES:
            probs.add(
                file, f"{path.stat().st_size} bytes: too large for a {BATCH_FILE} (at most {MAX_BYTES})"
            )
            return None
        text = path.read_bytes().decode("utf-8-sig")
    except OSError as e:
        probs.add(file, f"cannot read: {e.strerror}")
        return None
    except UnicodeDecodeError as e:
        data = path.read_bytes()
        probs.add(file, f"not UTF-8 text{encoding_hint(data)}", line=data[: e.start].count(b"\n") + 1)
        return None
    try:
        node = yaml.compose(text, Loader=yaml.SafeLoader)
        if alias := _alias_problem(node):
            probs.add(file, alias[0], line=alias[1])
            return None
        if dup := _duplicate_key(node):
            probs.add(file, f"key {dup[0]!r} appears twice in one mapping", line=dup[1])
            return None
        if odd := _not_plain(node):
            probs.add(file, odd[0], line=odd[1])
            return None
        data = yaml.safe_load(text)
    except RecursionError:  # nested thousands of levels deep: PyYAML's composer recurses per level
        probs.add(file, "not valid YAML: nested too deep to read (a real batch.yaml has a few levels)")
        return None
    except ValueError as e:  # a well-formed but impossible value, e.g. `recorded: 2026-13-45`
        probs.add(file, f"not valid YAML: {e}")
        return None
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        what = getattr(e, "problem", None) or str(e)
        probs.add(file, f"not valid YAML: {what}", line=None if mark is None else mark.line + 1)
        return None
    if not isinstance(data, dict):
        probs.add(file, "must be a mapping of keys to values (see rig-log/1)", line=1)
        return None
    try:
        meta = BatchMeta.model_validate(data)
    except ValidationError as e:
        # one Problem per line (a problem log keeps one per place): a misspelt key inside a mapping
        # written on one line is both "not permitted" and its right spelling "required"
        by_line: dict[int | None, list[str]] = {}
        for err in e.errors():
            loc = _without_tags(tuple(err["loc"]))
            key = ".".join(str(p) for p in loc) or "(top level)"
            got = err.get("input")
            shown = (
                f" (got {got!r})"
                if err["type"] != "missing" and isinstance(got, str | int | float | bool)
                else ""
            )
            by_line.setdefault(_yaml_line(node, loc), []).append(f"key {key}: {err['msg']}{shown}")
        for line, reasons in by_line.items():
            probs.add(file, "; ".join(reasons), line=line)
        return None
    ok = True
    if meta.batch_id != batch_dir.name:
        probs.add(
            file,
            f"key batch_id: {meta.batch_id!r} differs from the folder name {batch_dir.name!r}",
            line=_yaml_line(node, ("batch_id",)),
        )
        ok = False
    elif not is_valid_id(meta.batch_id):
        probs.add(
            file,
            f"key batch_id: {meta.batch_id!r} does not match {ID_PATTERN.pattern}",
            line=_yaml_line(node, ("batch_id",)),
        )
        ok = False
    if clash := sorted(RESERVED & set(meta.sensor.channels)):
        probs.add(
            file,
            f"key sensor.channels: {', '.join(map(repr, clash))} is reserved for ingest's own "
            "columns; rename the channel",
            line=_yaml_line(node, ("sensor", "channels")),
        )
        ok = False
    return meta if ok else None
