"""The resample stage's entry point: deterministic outputs and reports, set-aside trials reported."""

from __future__ import annotations

import json

import pandas as pd
import pyarrow.parquet as pq
import pytest
import typer

from needlecue_runtime.vocab import ID_COLUMNS, PHASES
from pipeline.stages import resample
from tests.signals.fabricate import fabricate, write_ingested


def test_stage_writes_deterministic_outputs_and_reports(tmp_path):
    # Given two ingested batches (counts + N with a known truth, no purpose; volts + mN, one channel,
    # no truth, a calibration batch),
    # a set-aside batch folder without trials.parquet, and a trial whose reference is too short
    ingested = tmp_path / "ingested"
    short = fabricate(seed=21, offset_s=0.1)
    short.t_s, short.force = short.t_s[:40], short.force[:40]
    write_ingested(
        ingested,
        "bench-a",
        {"t1": fabricate(seed=22, offset_s=0.21), "t2": fabricate(seed=23, offset_s=-0.26), "t3": short},
        channels=["fsr1", "fsr2", "fsr3"],
    )
    write_ingested(
        ingested,
        "bench-b",
        {"u1": fabricate(seed=24, offset_s=0.05, n_channels=1)},
        channels=["v0"],
        units="volts",
        ref_units="mN",
        angle=45.0,
        with_truth=False,
        purpose="calibration",
    )
    (ingested / "rejected").mkdir()
    (ingested / "rejected" / "problems.json").write_text("[]")
    params = tmp_path / "params.yaml"
    params.write_text("resample:\n  rate_hz: 30.0\n")

    # When the stage runs twice into two folders
    for k in (1, 2):
        resample.main(ingested, tmp_path / f"out{k}", tmp_path / f"rep{k}", params)

    # Then the outputs are byte-identical
    out1, out2 = tmp_path / "out1", tmp_path / "out2"
    names = sorted(p.name for p in out1.iterdir())
    assert names == ["bench-a.json", "bench-a.parquet", "bench-b.json", "bench-b.parquet"]
    for name in names:
        assert (out1 / name).read_bytes() == (out2 / name).read_bytes()
    assert (tmp_path / "rep1/offsets.csv").read_bytes() == (tmp_path / "rep2/offsets.csv").read_bytes()

    # And each batch keeps its channel names, in volts and newtons, with the documented columns
    a = pq.read_table(out1 / "bench-a.parquet").to_pandas()
    assert list(a.columns) == [*ID_COLUMNS, "fsr1", "fsr2", "fsr3", "fx", "fy", "fz"]
    assert sorted(a.trial_id.unique()) == ["t1", "t2"]
    assert (a.unit_id == "unit-bench-a").all()  # every row says which unit recorded it
    assert a[["fsr1", "fsr2", "fsr3"]].max().max() < 5.0
    b = pq.read_table(out1 / "bench-b.parquet").to_pandas()
    assert list(b.columns) == [*ID_COLUMNS, "v0", "fx", "fy", "fz"]
    assert b[["fx", "fy", "fz"]].abs().max().max() < 2.0  # N, not mN
    assert (b.angle_deg == 45.0).all() and set(b.phase) <= set(PHASES)
    assert (b.unit_id == "unit-bench-b").all()
    # And the batch's unit and purpose are kept next to its channels (no purpose: training)
    meta = json.loads((out1 / "bench-b.json").read_text())
    assert meta == {
        "batch_id": "bench-b",
        "channels": ["v0"],
        "rate_hz": 30.0,
        "unit_id": "unit-bench-b",
        "front_end": None,
        "purpose": "calibration",
        "samples_sha256": json.loads((ingested / "bench-b" / "batch.json").read_text())["samples_sha256"],
    }
    assert json.loads((out1 / "bench-a.json").read_text())["purpose"] == "training"

    # And the offsets report has one row per trial, the truth where known, the reason where set aside
    rep = pd.read_csv(tmp_path / "rep1/offsets.csv", dtype=str, keep_default_na=False).set_index("trial_id")
    assert list(rep.index) == ["t1", "t2", "t3", "u1"]
    assert (rep.loc[["t1", "t2", "u1"], "status"] == "ok").all()
    assert rep.loc["t3", "status"].startswith("set aside: ")
    assert abs(float(rep.loc["t1", "error_s"])) < 1 / 30 and abs(float(rep.loc["t2", "error_s"])) < 1 / 30
    assert rep.loc["u1", "true_offset_s"] == "" and rep.loc["u1", "error_s"] == ""
    assert int(rep.loc["t1", "n_grid"]) == int((a.trial_id == "t1").sum())
    summary = (tmp_path / "rep1/summary.md").read_text()
    assert "4 (3 ok, 1 set aside)" in summary and "Offset error" in summary
    assert (tmp_path / "rep1/offsets.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_bad_params_exit_1_with_the_reason(tmp_path, capsys):
    # Given a resample section with an impossible grid rate
    params = tmp_path / "params.yaml"
    params.write_text("resample:\n  rate_hz: -30\n")
    # When the stage runs / Then it stops with exit code 1 and one line naming the key
    with pytest.raises(typer.Exit) as exit_info:
        resample.main(tmp_path / "in", tmp_path / "out", tmp_path / "rep", params)
    assert exit_info.value.exit_code == 1
    err = capsys.readouterr().err
    assert err.startswith("resample: error: ") and "rate_hz" in err
    assert not (tmp_path / "out").exists()


def test_a_one_axis_batch_is_resampled_to_its_one_force_column(tmp_path):
    # Given an ingested batch whose reference records fz alone (reference.axes [fz]), in mN
    ingested = tmp_path / "ingested"
    trials = {"t1": fabricate(seed=31, offset_s=0.18), "t2": fabricate(seed=32, offset_s=-0.12)}
    write_ingested(
        ingested, "load-cell", trials, channels=["fsr1", "fsr2", "fsr3"], ref_units="mN", axes=("fz",)
    )
    params = tmp_path / "params.yaml"
    params.write_text("resample: {}\n")
    # When the stage runs
    resample.main(ingested, tmp_path / "out", tmp_path / "rep", params)
    # Then its table has that axis only, in N (no stand-in for fx and fy), every trial aligned
    table = pq.read_table(tmp_path / "out" / "load-cell.parquet")
    assert table.column_names == [*ID_COLUMNS, "fsr1", "fsr2", "fsr3", "fz"]
    frame = table.to_pandas()
    assert sorted(frame.trial_id.unique()) == ["t1", "t2"] and frame.fz.notna().all()
    assert frame.fz.abs().max() < 2.0 and set(frame.phase) == set(PHASES)
    offsets = pd.read_csv(tmp_path / "rep" / "offsets.csv")
    assert (offsets.status == "ok").all() and (offsets.error_s.abs() < 0.02).all()
    # And its .json has the keys of any batch's: the axes are the table's columns
    meta = json.loads((tmp_path / "out" / "load-cell.json").read_text())
    assert set(meta) == {
        "batch_id",
        "channels",
        "rate_hz",
        "unit_id",
        "front_end",
        "purpose",
        "samples_sha256",
    }
