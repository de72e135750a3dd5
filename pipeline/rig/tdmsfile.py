"""Reading a trial's reference stream from an NI TDMS file (`<trial>.ref.tdms`, npTDMS) into the frame
the CSV reader gives: trial_id, line, t_s, the force axes batch.yaml's `reference.axes` declares (fx,
fy, fz by default) (+ tx, ty, tz when all three are there).

The layout (docs/rig-log-format.md, "The reference stream as NI TDMS"): one group holds a channel per
declared axis (`fx`, `fy`, `fz` by default; optionally `tx`, `ty`, `tz`) of equal length, in
`reference.units`; the time is a `t_s` channel of seconds in that group, or else the waveform
properties NI writes on the force channels (`wf_increment` s per sample, `wf_start_offset` s). The
group is the one holding the first declared axis; a force axis there that batch.yaml does not
declare is a Problem, as in a CSV header. A TDMS file has no lines, so a Problem's
`line` is the 1-based sample number in its channel. Never raises on bad input.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from needlecue_runtime.vocab import AXES
from pipeline.rig.format import REF_TIME, REF_TORQUES, undeclared_axes
from pipeline.rig.problems import ProblemLog

TIME = REF_TIME
WF_INCREMENT, WF_OFFSET, UNIT = "wf_increment", "wf_start_offset", "unit_string"


def read_ref(
    path: Path,
    trial_id: str,
    unit: str,
    axes: Sequence[str],
    probs: ProblemLog,
    warn: Callable[[str], None],
) -> pd.DataFrame | None:
    """The reference stream of `path` (the force `axes`, batch.yaml's reference.axes, in `unit`, its
    reference.units), or None with Problems saying why it cannot be used."""
    from nptdms import TdmsFile

    file = str(path)

    def bad(reason: str, column: str | None = None, line: int | None = None) -> None:
        probs.add(file, reason, trial_id=trial_id, column=column, line=line)

    heard: list[str] = []
    try:
        # Opened as a file object, not a path, so that npTDMS reads the file itself and never a
        # `.tdms_index` beside it (which may be stale). Metadata now, data channel by channel.
        with _npTDMS_says(heard), path.open("rb") as handle, TdmsFile.open(handle) as tdms:
            frame = _frame(tdms, path.stat().st_size, trial_id, unit, tuple(axes), bad, warn, heard)
    # npTDMS raises many kinds of error on a damaged file (ValueError, KeyError, struct.error,
    # EOFError, ...): each means the same to a lab, so all are one Problem.
    except Exception as e:
        bad(f"not a readable TDMS file ({type(e).__name__}: {str(e)[:200]})")
        return None
    for message in dict.fromkeys(heard):
        warn(f"npTDMS: {message}")
    return frame


@contextmanager
def _npTDMS_says(heard: list[str]) -> Iterator[None]:
    """npTDMS's warnings (a file cut short, say) collected into `heard` instead of printed. npTDMS gives
    each module's logger its own console handler, and a logging set-up elsewhere (GX's) may disable
    them, so each is taken over while a file is read and then restored."""

    class Collect(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            heard.append(record.getMessage())

    names = [n for n in logging.root.manager.loggerDict if n.split(".")[0] == "nptdms"]
    loggers = [logging.getLogger(n) for n in names]
    saved = [(lg.handlers, lg.propagate, lg.disabled) for lg in loggers]
    collect = Collect(logging.WARNING)
    for lg in loggers:
        lg.handlers, lg.propagate, lg.disabled = [collect], False, False
    try:
        yield
    finally:
        for lg, (handlers, propagate, disabled) in zip(loggers, saved, strict=True):
            lg.handlers, lg.propagate, lg.disabled = handlers, propagate, disabled


def _frame(
    tdms: Any,
    size: int,
    trial_id: str,
    unit: str,
    forces: tuple[str, ...],
    bad: Callable[..., None],
    warn: Callable[[str], None],
    heard: list[str],
) -> pd.DataFrame | None:
    if not tdms.groups():
        said = f" (npTDMS: {heard[0]})" if heard else ""
        bad(f"no data: an empty or damaged TDMS file{said}")
        return None
    key = forces[0]  # the group of the forces is the one holding the first declared axis
    groups = [g for g in tdms.groups() if key in _names(g)]
    if len(groups) != 1:
        layout = _few(f"{g.name!r}: {_few(_names(g), ', ') or 'no channels'}" for g in tdms.groups())
        if groups:
            names = " and ".join(repr(g.name) for g in groups)
            bad(f"channel {key!r} is in groups {names}: keep one group of forces", key)
        else:
            bad(f"no group has a channel {key!r} (groups: {layout or 'none'})", key)
        return None
    group = groups[0]
    have = _names(group)
    missing = [c for c in forces if c not in have]
    for c in missing:
        declared = f"; batch.yaml's reference.axes declares {', '.join(forces)}" if forces != AXES else ""
        bad(f"missing channel {c!r} in group {group.name!r} (channels: {_few(have, ', ')}){declared}", c)
    undeclared = {c: why for c, why in undeclared_axes(forces).items() if c in have}
    for c, why in undeclared.items():
        bad(why.replace("column", "channel", 1), c)
    if missing or undeclared:
        return None
    torques = [c for c in REF_TORQUES if c in have]
    if torques and len(torques) != len(REF_TORQUES):
        warn(f"only {', '.join(torques)} of {', '.join(REF_TORQUES)} present; ignored")
        torques = []
    used = [*forces, *torques, *([TIME] if TIME in have else [])]
    if extra := [c for c in have if c not in used]:
        warn(f"extra channel(s) {_few(map(repr, extra), ', ')} ignored")

    channels = {c: group[c] for c in used}
    n = len(channels[key])
    ok = True
    for c, ch in channels.items():
        if len(ch) != n:
            cut = " (a file cut short?)" if heard else ""
            bad(f"channel {c!r} has {len(ch)} samples, {key!r} has {n}{cut}", c)
            ok = False
        elif not np.issubdtype(ch.dtype, np.number) or np.issubdtype(ch.dtype, np.complexfloating):
            bad(f"channel {c!r} holds {ch.dtype}, not real numbers", c)
            ok = False
        found = ch.properties.get(UNIT)
        if c in forces and found not in (None, "", unit):  # torques are in N·m, whatever `unit` is
            bad(f"channel {c!r} is in {found!r} but batch.yaml says reference.units: {unit}", c)
            ok = False
    if not ok:
        return None
    if n == 0:
        bad("empty stream: no samples")
        return None
    shifted = [m for m in heard if "not a multiple of the chunk size" in m]
    if shifted and not any("less data than expected" in m for m in heard):
        # A segment declaring fewer bytes than its channels need, not at a cut-off end: npTDMS
        # shares the shortfall out among the channels, which shifts non-interleaved data.
        bad(f"damaged file: a segment's data does not fit its channels (npTDMS: {shifted[0]})")
        return None
    if n * len(channels) > size:  # damaged metadata: reading would allocate more than the file holds
        bad(f"declares {n} samples per channel, more than its {size} bytes can hold: damaged file")
        return None

    values = {c: np.asarray(channels[c][:], dtype=np.float64) for c in used}
    if TIME not in values:
        t = _waveform_time(channels, forces, n, bad)
        if t is None:
            return None
        values[TIME] = t
    for c in used:
        for i in np.flatnonzero(np.isinf(values[c]))[:1]:  # NaN stays: GX reports missing values
            bad(f"{values[c][i]} is not a finite number", c, int(i) + 1)
    return pd.DataFrame(
        {
            "trial_id": pd.Series([trial_id] * n, dtype=object),
            "line": np.arange(1, n + 1, dtype=np.int64),
            **{c: values[c] for c in [TIME, *forces, *torques]},
        }
    )


def _waveform_time(
    channels: dict[str, Any], forces: Sequence[str], n: int, bad: Callable[..., None]
) -> np.ndarray | None:
    """Sample times from the force channels' waveform properties (the first declared axis's; the
    others must agree where given)."""
    key = forces[0]
    first = channels[key].properties
    step = first.get(WF_INCREMENT)
    if step is None:
        bad(f"no time: no {TIME!r} channel and no waveform property {WF_INCREMENT!r} on {key!r}")
        return None
    step, start = _number(step), _number(first.get(WF_OFFSET, 0.0))
    if step is None or start is None:
        bad(f"waveform properties {WF_INCREMENT!r} and {WF_OFFSET!r} must be numbers", key)
        return None
    if not (np.isfinite(step) and step > 0 and np.isfinite(start)):
        bad(f"{WF_INCREMENT!r} must be a positive number of seconds, got {step}", key)
        return None
    for c in forces[1:]:
        for name, mine in ((WF_INCREMENT, step), (WF_OFFSET, start)):
            other = channels[c].properties.get(name)
            if other is not None and _number(other) != mine:
                bad(f"waveform property {name!r} is {other}, {key!r} has {mine}", c)
                return None
    return start + step * np.arange(n, dtype=np.float64)


def _number(value: Any) -> float | None:
    """A property as a float ("0.005" and 0.005 agree), None if it is not a number."""
    try:
        return float(value)
    except (TypeError, ValueError):
        return None


def _few(names: Iterable[str], sep: str = "; ", most: int = 10) -> str:
    """The first `most` of `names` joined, and how many more: a file of thousands of channels gives a
    readable message."""
    names = list(names)
    more = f"{sep}... {len(names) - most} more" if len(names) > most else ""
    return sep.join(names[:most]) + more


def _names(group: Any) -> list[str]:
    return [ch.name for ch in group.channels()]
