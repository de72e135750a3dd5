"""One recording is used once: the one answer to "is this trial a copy of another?".

A trial repeats another when its samples are the same: both streams' values in order, their times
and names left out, as parsed from the rig log. A batch or trial copied under another name, read
from a gzip or TDMS copy, or copied with every timestamp shifted, has the same samples. Ingest
hashes each accepted trial's samples (`samples_sha256`, kept in the ingested batch.json and carried
by resample); `needlecue check` and the split stage both ask `repeats` which trials to set aside.
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterable, Mapping

import numpy as np
import pandas as pd

TrialKey = tuple[str, str]  # (batch_id, trial_id)
SAMPLES_KEY = "samples_sha256"  # {trial_id: hash} in the ingested batch.json and resample's .json
NOT_VALUES = ("trial_id", "line")  # the parser's bookkeeping columns, not samples


def samples_sha256(streams: Iterable[tuple[pd.DataFrame, str]], trial_id: str) -> str:
    """SHA-256 of one trial's samples in each (frame, its time column) stream, in order: every
    value column but the time, as float64."""
    h = hashlib.sha256()
    for frame, time_column in streams:
        rows = frame[frame["trial_id"].astype(str) == trial_id]
        values = rows.drop(columns=[*NOT_VALUES, time_column], errors="ignore")
        h.update(np.ascontiguousarray(values.to_numpy(dtype=np.float64)).tobytes())
        h.update(b"\0")
    return h.hexdigest()


def repeats(hashes: Mapping[TrialKey, str]) -> dict[TrialKey, TrialKey]:
    """{trial: the trial it repeats} for every trial whose samples hash is an earlier one's, in
    (batch, trial) order: the first keeps the recording, the others are set aside."""
    first: dict[str, TrialKey] = {}
    out = {}
    for key in sorted(hashes):
        original = first.setdefault(hashes[key], key)
        if original != key:
            out[key] = original
    return out


def reason(original: TrialKey) -> str:
    """Why a repeat of `original` is set aside."""
    return (
        f"the same samples as {original[0]}/{original[1]}: a recording is used once (a batch or trial "
        "copied under another name, from another file format, or with its timestamps shifted?)"
    )
