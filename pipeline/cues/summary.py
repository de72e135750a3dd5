"""The cues' figures from tracker runs: per model kind and method, confusion matrices (at the end of the
insertion and per frame during it), accuracy, recall within `cue_within_s`, the seconds into the
insertion until the cue is right and stays right to the end, and what a trainee sees.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from needlecue_runtime.cues.pack import CUES, DEVIATION_GROUPS, VERDICTS, cue_for_deviation


def deviation_group(dev_deg: float) -> str:
    d = round(abs(dev_deg), 6)
    return "0" if d == 0 else "15" if d == 15 else "30" if d == 30 else ">=45"


@dataclass
class Run:
    """One tracker run on one trial: the shown cue per frame (codes into CUES)."""

    kind: str
    method: str
    preset: float
    true_angle: float
    t: np.ndarray
    codes: np.ndarray
    ins_start: int
    ins_end: int
    angle_est: float | None = None
    alarm: bool = False
    unit: str | None = None  # the estimator unit that recorded the trial


def _pct(values: Sequence[float], q: float) -> float | None:
    return float(np.percentile(values, q)) if len(values) else None


def time_to_cue(t: np.ndarray, right: np.ndarray, start: int, end: int) -> float | None:
    """Seconds from frame `start` until the cue is right and stays right through frame `end`
    (0 if right throughout; None if wrong at `end`)."""
    ok = right[start : end + 1]
    if not len(ok) or not ok[-1]:
        return None
    wrong = np.flatnonzero(~ok)
    return 0.0 if not len(wrong) else float(t[start + wrong[-1] + 1] - t[start])


def _shown(codes: np.ndarray) -> np.ndarray:
    """Which cue codes are an angle cue shown to the trainee (continue, correct or stop)."""
    return (codes >= 1) & (codes <= len(VERDICTS))


def trainee_view(final: np.ndarray, frames: np.ndarray, wrong_ever: int) -> dict[str, float | None]:
    """What a trainee sees, from the confusion matrices (rows: true continue / correct / stop; columns:
    CUES) at the insertion's end and over its frames, and the insertions that showed a wrong cue at
    some frame: the share of insertions ending on a wrong cue, of insertions showing one at any time,
    of insertion frames showing one, and of insertion frames showing a cue at all (coverage)."""
    n, nf = int(final.sum()), int(frames.sum())
    cue_cols = slice(1, 1 + len(VERDICTS))

    def wrong(m: np.ndarray) -> int:
        return int(m[:, cue_cols].sum() - np.trace(m[:, cue_cols]))

    return {
        "wrong_final": wrong(final) / n if n else None,
        "wrong_ever": wrong_ever / n if n else None,
        "wrong_frames": wrong(frames) / nf if nf else None,
        "coverage_frames": int(frames[:, cue_cols].sum()) / nf if nf else None,
    }


def summarise_runs(
    runs: Sequence[Run], continue_below: float = 7.5, stop_from: float = 22.5, within_s: float = 3.0
) -> dict[str, Any]:
    """Confusion matrices, accuracy and time to cue of tracker runs, per (kind, method); and per true
    cue, the share of trials whose cue was right, and stayed right, within `within_s` of the insertion's
    start (their mean over the cues present: `balanced_within_s`)."""
    out: dict[str, Any] = {}
    for run in runs:
        true = VERDICTS.index(cue_for_deviation(run.true_angle - run.preset, continue_below, stop_from)) + 1
        d = out.setdefault(run.kind, {}).setdefault(
            run.method,
            {
                "final": np.zeros((3, len(CUES)), dtype=np.int64),
                "frames": np.zeros((3, len(CUES)), dtype=np.int64),
                "wrong_ever": 0,
                "ttc": {g: [] for g in DEVIATION_GROUPS},
                "n": {g: 0 for g in DEVIATION_GROUPS},
                "right_final": {g: 0 for g in DEVIATION_GROUPS},
                "alarms": 0,
                "in_time": np.zeros((3, 2), dtype=np.int64),  # per true cue: [trials, right within_s]
            },
        )
        seg = run.codes[run.ins_start : run.ins_end + 1]
        d["final"][true - 1, run.codes[run.ins_end]] += 1
        d["frames"][true - 1] += np.bincount(seg, minlength=len(CUES))
        d["wrong_ever"] += int(bool(np.any(_shown(seg) & (seg != true))))
        g = deviation_group(run.true_angle - run.preset)
        d["n"][g] += 1
        d["right_final"][g] += int(run.codes[run.ins_end] == true)
        d["alarms"] += int(run.alarm)
        ttc = time_to_cue(run.t, run.codes == true, run.ins_start, run.ins_end)
        d["ttc"][g].append(ttc)
        d["in_time"][true - 1] += (1, int(ttc is not None and ttc <= within_s + 1e-9))
    result: dict[str, Any] = {}
    for kind, methods in out.items():
        for method, d in methods.items():
            fin, frm = d["final"], d["frames"]
            ttc = {}
            for g in DEVIATION_GROUPS:
                vals = [v for v in d["ttc"][g] if v is not None]
                ttc[g] = {
                    "trials": d["n"][g],
                    "right_at_end": d["right_final"][g],
                    "never_right": d["n"][g] - len(vals),
                    "median_s": _pct(vals, 50),
                    "p90_s": _pct(vals, 90),
                    "seconds": sorted(vals),
                }
            per_class = {
                c: (float(fin[i, i + 1] / fin[i].sum()) if fin[i].sum() else None)
                for i, c in enumerate(VERDICTS)
            }
            in_time = d["in_time"]
            recall_in_time = {
                c: (float(in_time[i, 1] / in_time[i, 0]) if in_time[i, 0] else None)
                for i, c in enumerate(VERDICTS)
            }
            known = [v for v in recall_in_time.values() if v is not None]
            result.setdefault(kind, {})[method] = {
                "within_s": within_s,
                "recall_within_s": recall_in_time,
                "balanced_within_s": float(np.mean(known)) if known else None,
                "confusion_final": {
                    "rows_true": list(VERDICTS),
                    "cols_cue": list(CUES),
                    "counts": fin.tolist(),
                },
                "confusion_frames": {
                    "rows_true": list(VERDICTS),
                    "cols_cue": list(CUES),
                    "counts": frm.tolist(),
                },
                "accuracy_final": float(np.trace(fin[:, 1:]) / fin.sum()) if fin.sum() else None,
                "accuracy_frames": float(np.trace(frm[:, 1:]) / frm.sum()) if frm.sum() else None,
                "recall_final": per_class,
                "seen": trainee_view(fin, frm, d["wrong_ever"]),
                "time_to_cue": ttc,
                "force_alarm_trials": d["alarms"] if method == "combined" else None,
            }
    return result
