"""Physical plausibility at ingest: values no sensor gives, glitches, flat lines and recordings of
several insertions set the trial aside with a located reason; the rest of the batch goes on."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pytest

from pipeline.config import IngestParams
from pipeline.rig.check import check_batches
from tests.rig.batches import A, lines_of, replace_in, set_cell, write_lines


def flatten(path: Path) -> None:
    """Every force of a reference file 0: a disconnected sensor's stream."""
    rows = lines_of(path)
    write_lines(path, [rows[0], *(r.split(",")[0] + ",0,0,0" for r in rows[1:])])


def clip(path: Path, column: str, fraction: float) -> None:
    """A stream's `column` held at `fraction` of its peak (from its first value) wherever it went
    beyond: a saturated sensor or logger."""
    rows = lines_of(path)
    k = rows[0].split(",").index(column)
    values = [float(r.split(",")[k]) for r in rows[1:]]
    rest = values[0]
    peak = max(values, key=lambda v: abs(v - rest))
    top = rest + fraction * (peak - rest)
    out = [rows[0]]
    for r, v in zip(rows[1:], values, strict=True):
        cells = r.split(",")
        cells[k] = f"{top:g}" if (v - top) * (peak - rest) > 0 else cells[k]
        out.append(",".join(cells))
    write_lines(path, out)


def hold(path: Path, column: str, first: int, last: int, value: str) -> None:
    """`column` set to `value` on lines `first`..`last` of a stream file."""
    for line in range(first, last + 1):
        set_cell(path, line, column, value)


@dataclass(frozen=True)
class Case:
    name: str
    mutate: Callable[[Path], None]
    file: str  # the file blamed, in the batch folder
    line: int | None
    column: str | None
    reason: str  # a fragment of the reason
    params: IngestParams | None = None  # the defaults


CASES = [
    Case(
        "a glitch of hundreds of newtons (mN file)",
        lambda b: set_cell(b / "t001.ref.csv", 12, "fz", "300000"),
        "t001.ref.csv",
        12,
        "fz",
        "fz = 300000 outside [-50000, 50000] mN (the reference sensor's range",
    ),
    Case(
        "a glitch within the range",
        lambda b: set_cell(b / "t001.ref.csv", 40, "fx", "9000"),
        "t001.ref.csv",
        40,
        "fx",
        "glitch: fx = 9000 mN between",
    ),
    Case(
        "the range of the batch's sensor model, from params",
        lambda b: None,
        "t001.ref.csv",
        None,
        "fx",
        "outside [-500, 500] mN",
        IngestParams(reference_max_n_by_model={"ATI Nano17": 0.5}),
    ),
    Case(
        "a disconnected reference sensor",
        lambda b: flatten(b / "t001.ref.csv"),
        "t001.ref.csv",
        2,
        None,
        "reference stream constant over all 2001 samples (fx = 0, fy = 0, fz = 0): sensor disconnected?",
    ),
    Case(
        "a reference clipped at 40 % of its peak",
        lambda b: clip(b / "t001.ref.csv", "fz", 0.4),
        "t001.ref.csv",
        None,
        "fz",
        "fz clipped: held at",
    ),
    Case(
        "a dead estimator channel",
        lambda b: hold(b / "t001.fsr.csv", "top", 2, 500, "0.8"),
        "t001.fsr.csv",
        2,
        "top",
        "top constant at 0.8 over all 499 samples while left, right, bottom move: a dead or disconnected",
    ),
    Case(
        "an estimator channel saturated at its supply",
        lambda b: hold(b / "t001.fsr.csv", "left", 200, 230, "5"),
        "t001.fsr.csv",
        200,
        "left",
        "left clipped: held at 5 V, its maximum, for 0.6",
    ),
    Case(
        "a trial that names another estimator unit",
        lambda b: write_lines(
            b / "trials.csv",
            [
                f"{r},{u}"
                for r, u in zip(
                    lines_of(b / "trials.csv"),
                    ["unit_id", "est-other", "est-bench-01", "est-bench-01"],
                    strict=True,
                )
            ],
        ),
        "trials.csv",
        2,
        "unit_id",
        "unit_id 'est-other', but batch.yaml's sensor.unit_id is 'est-bench-01': a batch is recorded",
    ),
    Case(
        "counts declared as volts",
        lambda b: set_cell(b / "t001.fsr.csv", 7, "left", "512"),
        "t001.fsr.csv",
        7,
        "left",
        "left = 512 outside [0, 5] V (0 to sensor.vref_v, else ingest.max_volts",
    ),
    Case(
        "a recording longer than the robot's programme allows",
        lambda b: replace_in(b / "batch.yaml", "insertion_time_s: 5.0", "insertion_time_s: 1.0"),
        "t001.fsr.csv",
        None,
        "t_ms",
        "the recording lasts 9.97977 s: one insertion and retraction take 1.5 s by the robot's programme",
    ),
]


@pytest.mark.parametrize("case", CASES, ids=lambda c: c.name)
def test_an_implausible_stream_sets_its_trial_aside_with_a_located_reason(raw_dir: Path, case: Case) -> None:
    # given: the good hand-made batch with one implausible stream
    batch = raw_dir / A
    case.mutate(batch)
    # when: checked as ingest reads it
    [checked] = check_batches([raw_dir], case.params or IngestParams())
    # then: t001 is set aside, blamed at the file, line and column, for that reason
    found = [p for p in checked.problems if p.file == str(batch / case.file) and case.reason in p.reason]
    assert found, [str(p) for p in checked.problems]
    assert "t001" in checked.trials_set_aside
    if case.line is not None:
        assert found[0].line == case.line
    assert found[0].column == case.column
    # and trials with nothing wrong go on, unless the limit concerns them all
    if "programme" not in case.reason and "params" not in case.name:
        assert checked.trials_accepted == ["t002", "t003"]


def test_a_step_is_not_a_glitch(raw_dir: Path) -> None:
    # given: a reference force that drops by 8 N at one sample and stays there (a puncture's drop)
    ref = raw_dir / A / "t002.ref.csv"
    rows = lines_of(ref)
    for i in range(500, len(rows)):
        t, fx, fy, fz = rows[i].split(",")
        rows[i] = ",".join([t, str(float(fx) - 8000.0), fy, fz])
    write_lines(ref, rows)
    # when / then: the trial is accepted
    [checked] = check_batches([raw_dir], IngestParams())
    assert checked.problems == [] and checked.trials_accepted == ["t001", "t002", "t003"]
