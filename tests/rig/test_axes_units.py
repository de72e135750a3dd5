"""Any lab's reference sensor (issue 56): one force axis or three (`reference.axes`), in the units it
reports (`reference.units`: N, mN, g, kg, lbf), in CSV, gzip CSV and TDMS, every check on the
declared axes only."""

from __future__ import annotations

import gzip
import json
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from pipeline.config import IngestParams, ResampleParams
from pipeline.rig.format import NEWTONS_PER_UNIT
from pipeline.signals.one_batch import read_batch
from pipeline.signals.scaling import to_newtons
from tests.rig.batches import TRIALS, A, drop_column, gzip_file, replace_in, run, set_cell, to_tdms

MN_FIXTURE = "units: mN"  # lab-bench-a's reference is in mN


def _declare_axes(b: Path, axes: str) -> None:
    replace_in(b / "batch.yaml", "  frame: tissue\n", f"  frame: tissue\n  axes: {axes}\n")


def _keep_axes(b: Path, keep: list[str], trials: list[str] = TRIALS) -> None:
    """The reference files of `trials` with only `t_s` and the force axes `keep`."""
    for t in trials:
        for axis in ("fx", "fy", "fz"):
            if axis not in keep:
                drop_column(b / f"{t}.ref.csv", axis)


def _in_units(b: Path, unit: str) -> None:
    """lab-bench-a's reference (mN) rewritten in `unit`, the same forces (values as Python writes
    floats: read back exactly)."""
    replace_in(b / "batch.yaml", MN_FIXTURE, f"units: {unit}")
    for t in TRIALS:
        path = b / f"{t}.ref.csv"
        frame = pd.read_csv(path)
        for axis in ("fx", "fy", "fz"):
            frame[axis] = frame[axis] * 1e-3 / NEWTONS_PER_UNIT[unit]
        frame.to_csv(path, index=False)


def _problems(result, file: str) -> list:
    return [p for p in result.problems if Path(p.file).name == file]


# --------------------------------------------------------------------------- axes


def test_a_one_axis_reference_t_s_fz_declared_as_axes_fz_is_kept(raw_dir, tmp_path):
    # Given lab-bench-a recorded by a one-axis load cell: batch.yaml `axes: [fz]`, files `t_s,fz`
    b = raw_dir / A
    _declare_axes(b, "[fz]")
    _keep_axes(b, ["fz"])
    assert (b / "t001.ref.csv").read_text().splitlines()[0] == "t_s,fz"
    # When it is ingested
    result = run([raw_dir], tmp_path / "out")
    # Then every trial is kept, with only that axis, and batch.json says which axes were recorded
    assert result.problems == [] and result.accepted == [A]
    out = tmp_path / "out" / A
    assert list(pd.read_parquet(out / "ref.parquet").columns) == ["trial_id", "t_s", "fz"]
    assert json.loads((out / "batch.json").read_text())["reference"]["axes"] == ["fz"]


def test_the_default_axes_are_not_written_to_batch_json(raw_dir, tmp_path):
    # Given lab-bench-a saying `axes: [fz, fx, fy]` (all three, in another order) and a copy saying nothing
    run([raw_dir], tmp_path / "before")
    _declare_axes(raw_dir / A, "[fz, fx, fy]")
    # When ingested
    run([raw_dir], tmp_path / "after")
    # Then the outputs are those of the batch without the key: all three axes is the default
    for name in ("batch.json", "ref.parquet", "problems.json"):
        assert (tmp_path / "before" / A / name).read_bytes() == (tmp_path / "after" / A / name).read_bytes()


def test_an_axis_the_file_has_but_batch_yaml_does_not_declare_is_a_located_problem(raw_dir, tmp_path):
    # Given axes [fz], and t002's reference still holding fx, fy and fz
    b = raw_dir / A
    _declare_axes(b, "[fz]")
    _keep_axes(b, ["fz"], ["t001", "t003"])
    # When ingested
    result = run([raw_dir], tmp_path / "out")
    # Then t002 is set aside, its header's fx and fy named by file, line and column, in one line each
    found = {(p.line, p.column): p.reason for p in _problems(result, "t002.ref.csv")}
    assert set(found) == {(1, "fx"), (1, "fy")}
    assert "force axis that batch.yaml's reference.axes (fz) does not declare" in found[(1, "fx")]
    assert all("\n" not in str(p) for p in result.problems)
    assert result.batches[0].trials_accepted == ["t001", "t003"]


@pytest.mark.parametrize(
    ("declared", "kept", "missing"), [(None, ["fx", "fz"], "fy"), ("[fx, fz]", ["fz"], "fx")]
)
def test_an_axis_batch_yaml_declares_but_the_file_lacks_is_a_located_problem(
    raw_dir, tmp_path, declared, kept, missing
):
    # Given batch.yaml's axes (the default, or [fx, fz]) and t002's reference lacking one of them
    b = raw_dir / A
    if declared:
        _declare_axes(b, declared)
        _keep_axes(b, ["fx", "fz"], ["t001", "t003"])
    _keep_axes(b, kept, ["t002"])
    # When ingested
    result = run([raw_dir], tmp_path / "out")
    # Then t002 is set aside at its header, the missing column named
    [problem] = _problems(result, "t002.ref.csv")
    assert (problem.line, problem.column) == (1, missing)
    assert (
        problem.reason.startswith(f"missing column {missing!r}")
        and "reference.axes declares" in problem.reason
    )
    assert result.batches[0].trials_accepted == ["t001", "t003"]


def test_a_one_axis_reference_constant_over_the_trial_is_a_dead_sensor(raw_dir, tmp_path):
    # Given axes [fz] and t002's fz constant (no other axis to move beside it)
    b = raw_dir / A
    _declare_axes(b, "[fz]")
    _keep_axes(b, ["fz"])
    frame = pd.read_csv(b / "t002.ref.csv").assign(fz=0.0)
    frame.to_csv(b / "t002.ref.csv", index=False)
    # When ingested
    result = run([raw_dir], tmp_path / "out")
    # Then t002 is set aside as a flat line
    [problem] = _problems(result, "t002.ref.csv")
    assert "reference stream constant over all" in problem.reason and "fz = 0" in problem.reason
    assert result.batches[0].trials_accepted == ["t001", "t003"]


def test_a_dead_axis_is_judged_among_the_declared_axes_only(raw_dir, tmp_path):
    # Given axes [fx, fz] and t002's fx stuck at 0 while its fz moves
    b = raw_dir / A
    _declare_axes(b, "[fx, fz]")
    _keep_axes(b, ["fx", "fz"])
    frame = pd.read_csv(b / "t002.ref.csv").assign(fx=0.0)
    frame.to_csv(b / "t002.ref.csv", index=False)
    # When ingested
    result = run([raw_dir], tmp_path / "out")
    # Then fx is the dead channel, seen against fz alone
    [problem] = _problems(result, "t002.ref.csv")
    assert problem.column == "fx" and "while fz move" in problem.reason


@pytest.mark.parametrize(
    ("axes", "line", "reason"),
    [
        ("[]", 14, "key reference.axes: Value error, name at least one force axis of fx, fy, fz"),
        ("[fz, fz]", 14, "key reference.axes: Value error, lists fz more than once"),
        ("[fz, Fy]", 14, "key reference.axes.1: Input should be 'fx', 'fy' or 'fz' (got 'Fy')"),
    ],
)
def test_a_bad_reference_axes_sets_the_batch_aside_on_its_line(raw_dir, tmp_path, axes, line, reason):
    # Given batch.yaml's reference.axes empty, repeating an axis, or naming no axis
    _declare_axes(raw_dir / A, axes)
    # When ingested
    result = run([raw_dir], tmp_path / "out")
    # Then the batch is set aside by one problem on that line, naming the field
    [problem] = result.problems
    assert (Path(problem.file).name, problem.line) == ("batch.yaml", line)
    assert problem.reason == reason and result.accepted == []


def test_a_one_axis_reference_reads_the_same_from_gzip_csv_and_tdms(raw_dir, tmp_path):
    # Given the one-axis batch, and copies of it with the references gzip-compressed and as TDMS
    b = raw_dir / A
    _declare_axes(b, "[fz]")
    _keep_axes(b, ["fz"])
    run([raw_dir], tmp_path / "csv")
    for t in TRIALS:
        gzip_file(b / f"{t}.ref.csv")
    run([raw_dir], tmp_path / "gz")
    for t in TRIALS:
        path = b / f"{t}.ref.csv"
        path.write_bytes(gzip.decompress((b / f"{t}.ref.csv.gz").read_bytes()))
        (b / f"{t}.ref.csv.gz").unlink()
        to_tdms(path, unit="mN")  # replaces the CSV
    # When ingested, and the TDMS batch too
    result = run([raw_dir], tmp_path / "tdms")
    # Then all three give the same reference, with fz alone
    assert result.problems == []
    ref = {k: (tmp_path / k / A / "ref.parquet").read_bytes() for k in ("csv", "gz", "tdms")}
    assert ref["csv"] == ref["gz"] == ref["tdms"]
    assert list(pd.read_parquet(tmp_path / "tdms" / A / "ref.parquet").columns) == ["trial_id", "t_s", "fz"]


def test_a_tdms_channel_of_an_undeclared_axis_or_lacking_a_declared_one_is_a_located_problem(
    raw_dir, tmp_path
):
    # Given axes [fy, fz]: t001's TDMS holds fx, fy, fz; t002's holds fz alone
    b = raw_dir / A
    _declare_axes(b, "[fy, fz]")
    _keep_axes(b, ["fz"], ["t002"])
    _keep_axes(b, ["fy", "fz"], ["t003"])
    to_tdms(b / "t001.ref.csv", unit="mN")
    to_tdms(b / "t002.ref.csv", unit="mN")
    # When ingested
    result = run([raw_dir], tmp_path / "out")
    # Then t001's fx and t002's missing fy are named by file and channel
    assert [(p.column, "does not declare" in p.reason) for p in _problems(result, "t001.ref.tdms")] == [
        ("fx", True)
    ]
    [lacks] = _problems(result, "t002.ref.tdms")
    assert lacks.column == "fy" and lacks.reason.startswith("no group has a channel 'fy'")
    assert result.batches[0].trials_accepted == ["t003"]


# --------------------------------------------------------------------------- units


@pytest.mark.parametrize(
    ("unit", "newtons"),
    [("N", 1.0), ("mN", 1e-3), ("g", 9.80665e-3), ("kg", 9.80665), ("lbf", 4.4482216152605)],
)
def test_each_reference_unit_converts_to_newtons(unit, newtons):
    # Given two forces in `unit`, When converted, Then they are in N
    np.testing.assert_allclose(
        to_newtons(np.array([2.0, -0.5]), unit), [2.0 * newtons, -0.5 * newtons], rtol=1e-15
    )


def test_an_unknown_unit_fails_naming_the_field_and_the_allowed_values():
    with pytest.raises(
        ValueError,
        match=r"unknown reference units 'kN' \(reference.units is one of 'N', 'mN', 'g', 'kg', 'lbf'\)",
    ):
        to_newtons(np.array([1.0]), "kN")


def test_an_unknown_unit_in_batch_yaml_is_one_located_line_naming_the_allowed_values(raw_dir, tmp_path):
    # Given batch.yaml saying `units: kN`
    replace_in(raw_dir / A / "batch.yaml", MN_FIXTURE, "units: kN")
    # When ingested
    result = run([raw_dir], tmp_path / "out")
    # Then the batch is set aside by one problem on the line of reference.units
    [problem] = result.problems
    assert (Path(problem.file).name, problem.line) == ("batch.yaml", 12)
    assert problem.reason == "key reference.units: Input should be 'N', 'mN', 'g', 'kg' or 'lbf' (got 'kN')"
    assert "\n" not in str(problem)


def test_a_file_in_grams_and_one_in_newtons_of_the_same_force_give_the_same_newtons(raw_dir, tmp_path):
    # Given lab-bench-a's forces written in N, and again in grams (gram-force)
    rows = {}
    for unit in ("N", "g"):
        folder = tmp_path / unit
        shutil.copytree(raw_dir / A, folder / A)
        _in_units(folder / A, unit)
        # When each is read and resampled as the pipeline does
        batch = read_batch(folder / A, IngestParams(), ResampleParams())
        assert batch.problems == []
        rows[unit] = batch.rows
    # Then the resampled forces are the same newtons
    assert len(rows["N"]) > 100
    np.testing.assert_allclose(
        rows["g"][["fx", "fy", "fz"]], rows["N"][["fx", "fy", "fz"]], rtol=1e-9, atol=1e-12
    )


@pytest.mark.parametrize(
    ("unit", "peak", "out"),
    [("kg", 5.2, True), ("kg", 5.0, False), ("lbf", 11.5, True), ("g", 5000.0, False)],
)
def test_the_reference_range_is_judged_in_newtons_whatever_the_unit(raw_dir, tmp_path, unit, peak, out):
    # Given lab-bench-a in `unit`, one fz sample of t002 set to `peak` (5.2 kg = 51 N, 5 kg = 49 N,
    # 11.5 lbf = 51 N, 5000 g = 49 N; the limit is ingest.reference_max_n = 50 N)
    b = raw_dir / A
    _in_units(b, unit)
    set_cell(b / "t002.ref.csv", 1000, "fz", repr(peak))
    set_cell(b / "t002.ref.csv", 1001, "fz", repr(peak))  # two samples: a plateau, not a glitch
    # When ingested
    result = run([raw_dir], tmp_path / "out", IngestParams(reference_glitch_n=1000.0))
    # Then only a force beyond 50 N is out of range, and the reason says the limit in N
    ranged = [p for p in _problems(result, "t002.ref.csv") if "outside" in p.reason]
    assert bool(ranged) == out
    if out:
        assert ranged[0].line == 1000 and "±50 N" in ranged[0].reason and f"] {unit} (" in ranged[0].reason
