"""Reading rig-log/1 batches: a good hand-made batch goes through; every kind of bad input is set
aside precisely."""

from __future__ import annotations

import gzip
import json
import shutil
import struct
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from pipeline.config import IngestParams
from pipeline.rig import check
from pipeline.rig.format import BatchMeta
from pipeline.rig.problems import MAX_PER_COLUMN
from tests.helpers import tree_hash
from tests.rig.batches import (
    CHANNELS,
    TRIALS,
    A,
    cell,
    copy_batch,
    drop_column,
    gzip_file,
    lines_of,
    replace_in,
    run,
    set_cell,
    to_counts,
    to_tdms,
    write_lines,
)

# --------------------------------------------------------------------------- the good batch


def test_good_fixture_is_ingested_in_raw_units_with_metadata_kept(raw_dir, tmp_path):
    # Given the hand-made volts/mN batch
    before = tree_hash(raw_dir)
    # When it is ingested
    result = run([raw_dir], tmp_path / "out")
    # Then it is accepted without problems, trials sorted, extra column and unknown keys kept
    assert result.accepted == [A] and result.problems == [] and result.parsed == [A]
    out = tmp_path / "out" / A
    trials = pd.read_parquet(out / "trials.parquet")
    assert list(trials.columns) == ["trial_id", "angle_deg", "tissue_point", "note_offset_ms"]
    assert trials["trial_id"].tolist() == TRIALS
    assert trials["angle_deg"].tolist() == [30.0, 30.0, 45.0]
    assert trials["note_offset_ms"].tolist() == ["120", "-80", "200"]
    meta = json.loads((out / "batch.json").read_text())
    assert meta["operator"] == "bench fixture" and meta["sensor"]["supply_v"] == 5.0
    assert meta["source_dir"] == str(raw_dir / A)
    BatchMeta.model_validate({k: v for k, v in meta.items() if k != "source_dir"})
    # ... streams in raw units (volts, mN), channel order as in batch.yaml, float64
    fsr = pd.read_parquet(out / "fsr.parquet")
    assert list(fsr.columns) == ["trial_id", "t_ms", *CHANNELS]
    assert all(fsr[c].dtype == "float64" for c in ["t_ms", *CHANNELS])
    first = pd.read_csv(raw_dir / A / "t001.fsr.csv")
    pd.testing.assert_frame_equal(
        fsr[fsr.trial_id == "t001"].drop(columns="trial_id").reset_index(drop=True), first.astype("float64")
    )
    ref = pd.read_parquet(out / "ref.parquet")
    assert list(ref.columns) == ["trial_id", "t_s", "fx", "fy", "fz"]
    assert ref["fz"].max() > 500  # mN, not converted to N
    assert sorted(ref.trial_id.unique()) == TRIALS
    assert json.loads((out / "problems.json").read_text()) == []
    assert set(json.loads((out / "gx_results.json").read_text())) == {"trials", "fsr", "ref", "streams"}
    # ... and the raw folder is untouched
    assert tree_hash(raw_dir) == before


@pytest.mark.parametrize(
    ("line", "purpose"),
    [(None, "training"), ("purpose: training", "training"), ("purpose: calibration", "calibration")],
)
def test_purpose_is_training_unless_the_batch_says_calibration(raw_dir, tmp_path, line, purpose):
    # Given lab-bench-a without a purpose, or with one of the two allowed
    if line:
        replace_in(raw_dir / A / "batch.yaml", "operator:", f"{line}\noperator:")
    # When it is ingested
    result = run([raw_dir], tmp_path / "out")
    # Then it is accepted, and batch.json says what it is for
    assert result.accepted == [A] and result.problems == []
    assert json.loads((tmp_path / "out" / A / "batch.json").read_text())["purpose"] == purpose


def test_same_input_gives_the_same_output_bytes(raw_dir, tmp_path):
    # Given one raw folder
    # When it is ingested twice into two fresh output folders
    run([raw_dir], tmp_path / "out1")
    run([raw_dir], tmp_path / "out2")
    # Then every output file is byte-identical
    assert tree_hash(tmp_path / "out1") == tree_hash(tmp_path / "out2")


def test_tolerated_variations_are_accepted(raw_dir, tmp_path):
    # Given a batch with a BOM + CRLF trials.csv, reordered fsr columns with an extra one,
    # blank lines, and torques in every reference stream
    b = raw_dir / A
    (b / "trials.csv").write_bytes(b"\xef\xbb\xbf" + (b / "trials.csv").read_bytes().replace(b"\n", b"\r\n"))
    for t in TRIALS:
        rows = [r.split(",") for r in lines_of(b / f"{t}.fsr.csv")]
        order = [4, 2, 0, 1, 3]  # bottom, right, t_ms, left, top
        write_lines(
            b / f"{t}.fsr.csv",
            [",".join([*(r[i] for i in order), "21.5" if k else "temp_c"]) for k, r in enumerate(rows)]
            + [""],
        )
        ref = lines_of(b / f"{t}.ref.csv")
        write_lines(b / f"{t}.ref.csv", [ref[0] + ",tx,ty,tz", *(r + ",0.1,0.2,0.3" for r in ref[1:])])
    # When it is ingested
    result = run([raw_dir], tmp_path / "out")
    # Then it is accepted; the extra column is a warning; columns come out in batch.yaml order
    assert result.problems == [] and result.accepted == [A]
    # ... one warning line for the three files, not one per file
    assert [w for w in result.batches[0].warnings if "temp_c" in w] == [
        f"{raw_dir / A}: extra column(s) 'temp_c' ignored: t001.fsr.csv, t002.fsr.csv, t003.fsr.csv"
    ]
    fsr = pd.read_parquet(tmp_path / "out" / A / "fsr.parquet")
    assert list(fsr.columns) == ["trial_id", "t_ms", *CHANNELS]
    ref = pd.read_parquet(tmp_path / "out" / A / "ref.parquet")
    assert list(ref.columns) == ["trial_id", "t_s", "fx", "fy", "fz", "tx", "ty", "tz"]


def test_counts_batch_keeps_integer_counts(raw_dir, tmp_path):
    # Given the batch rewritten as 10-bit ADC counts
    to_counts(raw_dir / A)
    # When it is ingested
    result = run([raw_dir], tmp_path / "out")
    # Then counts come out unconverted (integers in [0, 1023], as float64)
    assert result.problems == []
    fsr = pd.read_parquet(tmp_path / "out" / A / "fsr.parquet")
    values = fsr[CHANNELS].to_numpy()
    assert (values == values.round()).all() and values.min() >= 0 and values.max() <= 1023


# --------------------------------------------------------------------------- other forms of the files


def _parquets(out: Path) -> dict[str, bytes]:
    return {name: (out / A / name).read_bytes() for name in ("trials.parquet", "fsr.parquet", "ref.parquet")}


def test_gzip_csv_and_tdms_reference_ingest_to_the_same_bytes_as_plain_csv(raw_dir, lab_bench_a, tmp_path):
    # Given the batch as plain CSV, and a copy whose trials.csv and estimator streams are gzip-compressed
    # and whose reference streams are NI TDMS files written by npTDMS (time as a t_s channel, units
    # said by each channel's unit_string), with the .tdms_index NI software writes beside them
    other = tmp_path / "other"
    b = other / A
    shutil.copytree(lab_bench_a, b)
    gzip_file(b / "trials.csv")
    for t in TRIALS:
        gzip_file(b / f"{t}.fsr.csv")
        tdms = to_tdms(b / f"{t}.ref.csv", unit="mN")
        tdms.with_suffix(".tdms_index").write_bytes(b"TDSh")
    before = tree_hash(other)
    # When both are ingested
    plain = run([raw_dir], tmp_path / "out-plain")
    forms = run([other], tmp_path / "out-forms")
    # Then both are accepted without problems or warnings, into byte-identical Parquet files
    assert plain.problems == forms.problems == [] and forms.accepted == [A]
    assert forms.batches[0].warnings == []
    assert _parquets(tmp_path / "out-plain") == _parquets(tmp_path / "out-forms")
    # ... and `needlecue check` agrees, naming no problem
    assert check.check_folders([other], IngestParams()) == []
    assert tree_hash(other) == before


def test_tdms_time_from_ni_waveform_properties(raw_dir, tmp_path):
    # Given reference streams as TDMS with no t_s channel: NI's wf_increment and wf_start_offset instead
    # (fz's increment written as text, as some writers do: it agrees with fx's number)
    b = raw_dir / A
    csv_ref = pd.read_csv(b / "t001.ref.csv")
    for t in TRIALS:
        step = float(np.median(np.diff(pd.read_csv(b / f"{t}.ref.csv")["t_s"])))
        to_tdms(b / f"{t}.ref.csv", time="waveform", properties={"fz": {"wf_increment": repr(step)}})
    # When the batch is ingested
    result = run([raw_dir], tmp_path / "out")
    # Then it is accepted; the times are start + k * increment, the forces exactly the CSV's
    assert result.problems == [] and result.accepted == [A]
    ref = pd.read_parquet(tmp_path / "out" / A / "ref.parquet")
    first = ref[ref.trial_id == "t001"]
    np.testing.assert_allclose(first["t_s"], csv_ref["t_s"], rtol=0, atol=1e-12)
    np.testing.assert_array_equal(
        first[["fx", "fy", "fz"]].to_numpy(), csv_ref[["fx", "fy", "fz"]].to_numpy()
    )


def test_tdms_torques_in_newton_metres_are_kept_beside_forces_in_millinewtons(raw_dir, tmp_path):
    # Given TDMS reference streams with forces in mN (as batch.yaml says) and torques in N·m
    b = raw_dir / A
    for t in TRIALS:
        ref = pd.read_csv(b / f"{t}.ref.csv")
        ref[["tx", "ty", "tz"]] = ref[["fx", "fy", "fz"]].to_numpy() * 1e-5
        ref.to_csv(b / f"{t}.ref.csv", index=False)
        torque = {c: {"unit_string": "N·m"} for c in ("tx", "ty", "tz")}
        to_tdms(b / f"{t}.ref.csv", unit="mN", properties=torque)
    # When the batch is ingested
    result = run([raw_dir], tmp_path / "out")
    # Then it is accepted with its torques: their unit is not the forces'
    assert result.problems == [] and result.accepted == [A]
    ref = pd.read_parquet(tmp_path / "out" / A / "ref.parquet")
    assert {"tx", "ty", "tz"} <= set(ref.columns)


def test_a_tdms_file_of_many_extra_channels_is_named_in_a_warning_of_readable_length(raw_dir, tmp_path):
    # Given a reference stream in TDMS whose forces' group also holds 50 other channels
    b = raw_dir / A
    ref = pd.read_csv(b / "t001.ref.csv")
    for k in range(50):
        ref[f"aux{k:02d}"] = 0.0
    ref.to_csv(b / "t001.ref.csv", index=False)
    to_tdms(b / "t001.ref.csv")
    # When the batch is ingested
    result = run([raw_dir], tmp_path / "out")
    # Then the trial is used, with one warning naming the first ten and how many more
    assert result.problems == [] and result.batches[0].trials_accepted == TRIALS
    (said,) = [w for w in result.batches[0].warnings if "extra channel" in w]
    assert "'aux00', 'aux01'" in said and "'aux09', ... 40 more ignored" in said and "aux10" not in said


def test_a_tdms_file_without_a_trial_row_is_reported_and_not_ingested(raw_dir, tmp_path):
    # Given a reference stream in TDMS for a trial trials.csv does not list
    b = raw_dir / A
    shutil.copy(b / "t001.ref.csv", b / "t009.ref.csv")
    to_tdms(b / "t009.ref.csv")
    # When the batch is ingested
    result = run([raw_dir], tmp_path / "out")
    # Then it is named as having no row; the listed trials go through
    assert [(Path(p.file).name, p.reason) for p in result.problems] == [
        ("t009.ref.tdms", "no row for trial 't009' in trials.csv: file not ingested")
    ]
    assert result.batches[0].trials_accepted == TRIALS


def test_a_gzip_file_that_inflates_beyond_the_limit_is_refused(raw_dir, tmp_path, monkeypatch):
    # Given a gzip-compressed estimator stream, and a limit below its inflated size
    from pipeline.rig import csvfile

    gz = gzip_file(raw_dir / A / "t002.fsr.csv")
    monkeypatch.setattr(csvfile, "MAX_GUNZIPPED_BYTES", 2**20 // 100)
    # When the batch is ingested
    result = run([raw_dir], tmp_path / "out")
    # Then that trial is set aside with the reason, the others go on
    assert [(p.file, p.reason) for p in result.problems] == [
        (str(gz), "decompresses to more than 0 MiB: refused")
    ]
    assert result.batches[0].trials_accepted == ["t001", "t003"]


# --------------------------------------------------------------------------- bad input corpus


@dataclass(frozen=True)
class Bad:
    """Break one thing in lab-bench-a; expect this Problem and this much set aside."""

    id: str
    mutate: Callable[[Path], None]
    file: str  # file name the Problem must name
    reason: str  # substring of its reason
    line: int | None = None  # expected line, if any
    column: str | None = None  # expected column, if any
    batch: bool = False  # whole batch set aside?
    trials: tuple[str, ...] = ("t002",)  # trials set aside (if not the whole batch)
    accepted: tuple[str, ...] | None = None  # default: the other trials


# nine levels of nine aliases: 9**9 nodes once expanded, a few hundred bytes of text
ALIAS_BOMB = "a0: &a0 [x, x, x, x, x, x, x, x, x]\n" + "".join(
    f"a{i}: &a{i} [{', '.join([f'*a{i - 1}'] * 9)}]\n" for i in range(1, 9)
)


def _fsr(t: str = "t002") -> str:
    return f"{t}.fsr.csv"


def _ref(t: str = "t002") -> str:
    return f"{t}.ref.csv"


def _dup_time(b: Path) -> None:
    set_cell(b / _fsr(), 20, "t_ms", cell(b / _fsr(), 19, "t_ms"))


def _time_back(b: Path, name: str, col: str) -> None:
    set_cell(b / name, 30, col, "0.0001")


def _few_samples(b: Path) -> None:
    write_lines(b / _fsr(), lines_of(b / _fsr())[:6])


def _slow_rate(b: Path) -> None:
    rows = [r.split(",") for r in lines_of(b / _fsr())]
    write_lines(
        b / _fsr(), [",".join(rows[0])] + [",".join([str(float(r[0]) * 1000), *r[1:]]) for r in rows[1:]]
    )


def _not_utf8(b: Path) -> None:
    data = (b / _ref()).read_bytes().split(b"\n")
    data[4] = data[4] + b"\xff"
    (b / _ref()).write_bytes(b"\n".join(data))


def _counts_then(line: int, value: str) -> Callable[[Path], None]:
    def mutate(b: Path) -> None:
        to_counts(b)
        set_cell(b / _fsr(), line, "top", value)

    return mutate


def _malformed(b: Path) -> None:
    rows = lines_of(b / _fsr())
    rows[11] += ",0.5"
    write_lines(b / _fsr(), rows)


def _drop_header(b: Path) -> None:
    write_lines(b / _fsr(), lines_of(b / _fsr())[1:])


def _all_refs_gone(b: Path) -> None:
    for t in TRIALS:
        (b / _ref(t)).unlink()


def _rename(src: Path, name: str) -> None:
    src.rename(src.with_name(name))


def _truncate(path: Path, keep: int) -> None:
    path.write_bytes(path.read_bytes()[:keep])


def _gzip_cut(b: Path) -> None:
    gz = gzip_file(b / _ref())
    _truncate(gz, gz.stat().st_size // 2)


def _tdms_segment_short(ref: Path) -> None:
    """A TDMS file whose only segment declares (and holds) 100 samples' bytes fewer than its channels
    need, with nothing cut off at the end: the lead-in's next-segment offset says where it ends."""
    tdms = to_tdms(ref)
    data = bytearray(tdms.read_bytes())
    lead_in = 28  # "TDSm", ToC mask, version, next-segment offset (u64 at 12), raw-data offset
    (length,) = struct.unpack_from("<Q", data, 12)
    length -= 100 * 8
    struct.pack_into("<Q", data, 12, length)
    tdms.write_bytes(bytes(data[: lead_in + length]))


def _tdms_two_groups(ref: Path) -> None:
    from nptdms import ChannelObject, TdmsFile, TdmsWriter

    tdms = to_tdms(ref)
    group = TdmsFile.read(tdms)["reference"]
    with TdmsWriter(tdms, mode="a") as w:
        w.write_segment([ChannelObject("copy", c.name, c[:]) for c in group.channels()])


def _declare_front_end(batch: Path, flow: str) -> None:
    """batch.yaml with `sensor.front_end: <flow>` on line 10, after the `supply_v` metadata line."""
    replace_in(
        batch / "batch.yaml",
        "kept as metadata\n",
        f"kept as metadata\n  front_end: {flow}\n",
    )


BAD = [
    # batch.yaml: the whole batch is set aside
    Bad(
        "missing batch.yaml",
        lambda b: (b / "batch.yaml").unlink(),
        "batch.yaml",
        "missing batch.yaml",
        batch=True,
    ),
    Bad(
        "batch.yaml not YAML",
        lambda b: replace_in(
            b / "batch.yaml", "channels: [left, right, top, bottom]", "channels: [left, right, top, bottom"
        ),
        "batch.yaml",
        "not valid YAML",
        line=8,
        batch=True,
    ),
    Bad(
        "batch.yaml not a mapping",
        lambda b: (b / "batch.yaml").write_text("- rig-log/1\n"),
        "batch.yaml",
        "must be a mapping",
        line=1,
        batch=True,
    ),
    Bad(
        "batch_id differs from folder",
        lambda b: replace_in(b / "batch.yaml", "batch_id: lab-bench-a", "batch_id: lab-bench-z"),
        "batch.yaml",
        "differs from the folder name",
        line=2,
        batch=True,
    ),
    Bad(
        "unknown format",
        lambda b: replace_in(b / "batch.yaml", "rig-log/1", "rig-log/2"),
        "batch.yaml",
        "key format",
        line=1,
        batch=True,
    ),
    Bad(
        "sensor.front_end with a misspelt key",
        lambda b: _declare_front_end(b, "{circuit: divider, supply_v: 5.0, fixed_ohm: 10.0}"),
        "batch.yaml",
        "key sensor.front_end.fixed_ohm: Extra inputs are not permitted",
        line=10,
        batch=True,
    ),
    Bad(
        "sensor.front_end of an unknown circuit",
        lambda b: _declare_front_end(b, "{circuit: wheatstone}"),
        "batch.yaml",
        "key sensor.front_end: Input tag 'wheatstone'",
        line=10,
        batch=True,
    ),
    Bad(
        "sensor.front_end with the FSR nowhere",
        lambda b: _declare_front_end(b, "{circuit: divider, supply_v: 5.0, fixed_kohm: 10.0, fsr_at: top}"),
        "batch.yaml",
        "key sensor.front_end.fsr_at: Input should be 'supply' or 'ground'",
        line=10,
        batch=True,
    ),
    Bad(
        "reference.clock neither separate nor shared",
        lambda b: replace_in(b / "batch.yaml", "  frame: tissue\n", "  frame: tissue\n  clock: host\n"),
        "batch.yaml",
        "key reference.clock: Input should be 'separate' or 'shared'",
        line=14,
        batch=True,
    ),
    Bad(
        "sensor.units missing",
        lambda b: replace_in(b / "batch.yaml", "  units: volts\n", ""),
        "batch.yaml",
        "key sensor.units: Field required",
        line=6,
        batch=True,
    ),
    Bad(
        "counts without adc_bits",
        lambda b: replace_in(b / "batch.yaml", "units: volts", "units: counts"),
        "batch.yaml",
        "adc_bits",
        line=6,
        batch=True,
    ),
    Bad(
        "wrong type in batch.yaml",
        lambda b: replace_in(b / "batch.yaml", "units: mN", "units: kN"),
        "batch.yaml",
        "key reference.units",
        line=12,
        batch=True,
    ),
    Bad(
        "duplicate key in batch.yaml",
        lambda b: replace_in(b / "batch.yaml", "operator:", "batch_id: x\noperator:"),
        "batch.yaml",
        "'batch_id' appears twice",
        line=15,
        batch=True,
    ),
    Bad(
        "channel named like an ingest column",
        lambda b: replace_in(b / "batch.yaml", "bottom]", "trial_id]"),
        "batch.yaml",
        "reserved",
        line=7,
        batch=True,
    ),
    Bad(
        "recursive alias in batch.yaml",
        lambda b: replace_in(b / "batch.yaml", "operator:", "loop: &loop\n  - *loop\noperator:"),
        "batch.yaml",
        "a recursive alias",
        line=15,
        batch=True,
    ),
    Bad(
        "YAML alias bomb in batch.yaml",
        lambda b: replace_in(b / "batch.yaml", "operator:", ALIAS_BOMB + "operator:"),
        "batch.yaml",
        "aliases expand the document beyond 10000 nodes",
        batch=True,
    ),
    Bad(
        "batch.yaml nested thousands of levels deep",
        lambda b: replace_in(
            b / "batch.yaml", "operator:", "deep: " + "[" * 3000 + "]" * 3000 + "\noperator:"
        ),
        "batch.yaml",
        "nested too deep to read",
        batch=True,
    ),
    Bad(
        "a non-finite number in batch.yaml",
        lambda b: replace_in(b / "batch.yaml", "insertion_time_s: 5.0", "insertion_time_s: .nan"),
        "batch.yaml",
        ".nan is not a finite number",
        line=14,
        batch=True,
    ),
    Bad(
        "binary data in batch.yaml",
        lambda b: replace_in(b / "batch.yaml", "operator:", "blob: !!binary /w==\noperator:"),
        "batch.yaml",
        "binary data (!!binary): batch.yaml holds plain values only",
        line=15,
        batch=True,
    ),
    Bad(
        "channels as a YAML set",
        lambda b: replace_in(
            b / "batch.yaml", "[left, right, top, bottom]", "!!set {left, right, top, bottom}"
        ),
        "batch.yaml",
        "a set (!!set)",
        line=7,
        batch=True,
    ),
    Bad(
        "a unit id that is a path",
        lambda b: replace_in(b / "batch.yaml", "unit_id: est-bench-01", 'unit_id: "../../tmp/escaped"'),
        "batch.yaml",
        "key sensor.unit_id: String should match pattern",
        line=6,
        batch=True,
    ),
    Bad(
        "channel named like a reference axis",
        lambda b: replace_in(b / "batch.yaml", "bottom]", "fx]"),
        "batch.yaml",
        "'fx' is reserved",
        line=7,
        batch=True,
    ),
    Bad(
        "channel named like a processed column",
        lambda b: replace_in(b / "batch.yaml", "bottom]", "phase]"),
        "batch.yaml",
        "'phase' is reserved",
        line=7,
        batch=True,
    ),
    Bad(
        "purpose typo in batch.yaml",
        lambda b: replace_in(b / "batch.yaml", "operator:", "purpose: calib\noperator:"),
        "batch.yaml",
        "key purpose: Input should be 'training' or 'calibration' (got 'calib')",
        line=15,
        batch=True,
    ),
    Bad(
        "impossible date in batch.yaml",
        lambda b: replace_in(b / "batch.yaml", "recorded: 2025-11-20", "recorded: 2025-13-45"),
        "batch.yaml",
        "month must be in 1..12",
        batch=True,
    ),
    # trials.csv
    Bad(
        "missing trials.csv",
        lambda b: (b / "trials.csv").unlink(),
        "trials.csv",
        "trials.csv is missing (and no trials.csv.gz)",
        batch=True,
    ),
    Bad(
        "trials.csv without tissue_point",
        lambda b: drop_column(b / "trials.csv", "tissue_point"),
        "trials.csv",
        "missing column 'tissue_point'",
        line=1,
        column="tissue_point",
        batch=True,
    ),
    Bad(
        "trials.csv without rows",
        lambda b: write_lines(b / "trials.csv", lines_of(b / "trials.csv")[:1]),
        "trials.csv",
        "lists no trials",
        batch=True,
    ),
    Bad("every trial unusable", _all_refs_gone, "trials.csv", "no usable trial", batch=True),
    Bad(
        "bad trial_id",
        lambda b: set_cell(b / "trials.csv", 3, "trial_id", "t 002"),
        "trials.csv",
        "does not match",
        line=3,
        column="trial_id",
        trials=("t 002",),
        accepted=("t001", "t003"),
    ),
    Bad(
        "trial_id that is a path",
        lambda b: set_cell(b / "trials.csv", 3, "trial_id", "../t002"),
        "trials.csv",
        "does not match",
        line=3,
        column="trial_id",
        trials=("../t002",),
        accepted=("t001", "t003"),
    ),
    Bad(
        "text angle",
        lambda b: set_cell(b / "trials.csv", 3, "angle_deg", "thirty"),
        "trials.csv",
        "text 'thirty' in a number column",
        line=3,
        column="angle_deg",
    ),
    Bad(
        "missing angle",
        lambda b: set_cell(b / "trials.csv", 3, "angle_deg", ""),
        "trials.csv",
        "missing value",
        line=3,
        column="angle_deg",
    ),
    Bad(
        "angle out of range",
        lambda b: set_cell(b / "trials.csv", 3, "angle_deg", "3000"),
        "trials.csv",
        "not an angle",
        line=3,
        column="angle_deg",
    ),
    Bad(
        "empty tissue_point",
        lambda b: set_cell(b / "trials.csv", 3, "tissue_point", " "),
        "trials.csv",
        "tissue_point is empty",
        line=3,
        column="tissue_point",
    ),
    Bad(
        "duplicate trial_id",
        lambda b: write_lines(b / "trials.csv", [*lines_of(b / "trials.csv"), "t002,P3,45,0"]),
        "trials.csv",
        "listed more than once",
        line=5,
        column="trial_id",
    ),
    Bad(
        "trials.csv row with too many fields",
        lambda b: replace_in(b / "trials.csv", "t002,P2,30,-80", "t002,P2,30,-80,x"),
        "trials.csv",
        "row has 5 fields, the header has 4",
        line=3,
    ),
    # trials vs files
    Bad("trial without its fsr file", lambda b: (b / _fsr()).unlink(), _fsr(), "is missing"),
    Bad(
        "trial without its ref file",
        lambda b: (b / _ref()).unlink(),
        _ref(),
        "t002.ref.csv is missing (and no t002.ref.csv.gz nor t002.ref.tdms)",
    ),
    Bad(
        "a folder where a stream file should be",
        lambda b: ((b / _fsr()).unlink(), (b / _fsr()).mkdir()),
        _fsr(),
        "is not a regular file",
    ),
    Bad(
        "stream file without a trial row",
        lambda b: shutil.copy(b / _fsr("t001"), b / _fsr("t009")),
        _fsr("t009"),
        "no row for trial 't009'",
        trials=(),
    ),
    # stream structure
    Bad("empty fsr file", lambda b: (b / _fsr()).write_text(""), _fsr(), "empty file"),
    Bad(
        "fsr header only", lambda b: write_lines(b / _fsr(), lines_of(b / _fsr())[:1]), _fsr(), "empty stream"
    ),
    Bad(
        "fsr lacks a channel",
        lambda b: drop_column(b / _fsr(), "top"),
        _fsr(),
        "missing column 'top'",
        line=1,
        column="top",
    ),
    Bad(
        "fsr with extra-only columns",
        lambda b: replace_in(b / _fsr(), "t_ms,left,right,top,bottom", "a,b,c,d,e"),
        _fsr(),
        "missing column 't_ms'",
        line=1,
        column="t_ms",
    ),
    Bad("fsr without header row", _drop_header, _fsr(), "is the header row missing?", line=1, column="t_ms"),
    Bad(
        "ref lacks a force column",
        lambda b: drop_column(b / _ref(), "fz"),
        _ref(),
        "missing column 'fz'",
        line=1,
        column="fz",
    ),
    Bad(
        "ref column twice",
        lambda b: replace_in(b / _ref(), "t_s,fx,fy,fz", "t_s,fx,fy,fy"),
        _ref(),
        "column 'fy' appears 2 times",
        line=1,
        column="fy",
    ),
    Bad("fsr row with a field too many", _malformed, _fsr(), "row has 6 fields, the header has 5", line=12),
    Bad("ref not UTF-8", _not_utf8, _ref(), "not UTF-8", line=5),
    Bad(
        "fsr saved as UTF-16",
        lambda b: (b / _fsr()).write_bytes((b / _fsr()).read_text().encode("utf-16")),
        _fsr(),
        "it looks like UTF-16; save it as UTF-8",
    ),
    Bad(
        "ref saved as Windows-1252",
        lambda b: (b / _ref()).write_bytes(
            (b / _ref()).read_text().replace("t_s,", "t_s_µ,", 1).encode("cp1252")
        ),
        _ref(),
        "it looks like Windows-1252 (cp1252); save it as UTF-8",
    ),
    # values
    Bad(
        "text in a number column",
        lambda b: set_cell(b / _fsr(), 10, "right", "abc"),
        _fsr(),
        "text 'abc' in a number column",
        line=10,
        column="right",
    ),
    Bad(
        "NaN value",
        lambda b: set_cell(b / _ref(), 40, "fy", "NaN"),
        _ref(),
        "missing value",
        line=40,
        column="fy",
    ),
    Bad(
        "empty cell",
        lambda b: set_cell(b / _fsr(), 7, "left", ""),
        _fsr(),
        "missing value",
        line=7,
        column="left",
    ),
    Bad(
        "infinite value",
        lambda b: set_cell(b / _ref(), 8, "fx", "inf"),
        _ref(),
        "not a finite number",
        line=8,
        column="fx",
    ),
    Bad(
        "count above the ADC range",
        _counts_then(15, "1024"),
        _fsr(),
        "outside the ADC range [0, 1023]",
        line=15,
        column="top",
    ),
    Bad("negative count", _counts_then(16, "-1"), _fsr(), "outside the ADC range", line=16, column="top"),
    Bad("fractional count", _counts_then(17, "511.5"), _fsr(), "not an integer", line=17, column="top"),
    # time and rate
    Bad(
        "duplicate timestamp",
        _dup_time,
        _fsr(),
        "time does not increase: step of 0 ms",
        line=20,
        column="t_ms",
    ),
    Bad(
        "fsr time goes back",
        lambda b: _time_back(b, _fsr(), "t_ms"),
        _fsr(),
        "time does not increase",
        line=30,
        column="t_ms",
    ),
    Bad(
        "ref time goes back",
        lambda b: _time_back(b, _ref(), "t_s"),
        _ref(),
        "time does not increase",
        line=30,
        column="t_s",
    ),
    Bad("too few samples", _few_samples, _fsr(), "only 5 samples"),
    Bad("implausible rate", _slow_rate, _fsr(), "sample rate", column="t_ms"),
    # the other forms: gzip-compressed CSV, the reference stream as NI TDMS (written by npTDMS)
    Bad(
        "gzip: text in a cell",
        lambda b: (set_cell(b / _fsr(), 9, "left", "oops"), gzip_file(b / _fsr())),
        _fsr() + ".gz",
        "text 'oops' in a number column",
        line=9,
        column="left",
    ),
    Bad("gzip: cut short", _gzip_cut, _ref() + ".gz", "not a readable gzip file"),
    Bad(
        "gzip: not gzip", lambda b: _rename(b / _ref(), _ref() + ".gz"), _ref() + ".gz", "not a readable gzip"
    ),
    Bad(
        "trials.csv and trials.csv.gz",
        lambda b: (b / "trials.csv.gz").write_bytes(gzip.compress((b / "trials.csv").read_bytes())),
        "trials.csv",
        "trials.csv and trials.csv.gz both exist: keep one of them",
        batch=True,
    ),
    Bad(
        "ref as CSV and as TDMS",
        lambda b: (
            shutil.copy(b / _ref(), b / "keep.csv"),
            to_tdms(b / _ref()),
            _rename(b / "keep.csv", _ref()),
        ),
        _ref(),
        "t002.ref.csv and t002.ref.tdms both exist",
    ),
    Bad(
        "tdms: no channel fz",
        lambda b: (drop_column(b / _ref(), "fz"), to_tdms(b / _ref())),
        "t002.ref.tdms",
        "missing channel 'fz' in group 'reference'",
        column="fz",
    ),
    Bad(
        "tdms: forces in two groups",
        lambda b: _tdms_two_groups(b / _ref()),
        "t002.ref.tdms",
        "channel 'fx' is in groups 'reference' and 'copy'",
        column="fx",
    ),
    Bad("tdms: no time", lambda b: to_tdms(b / _ref(), time="none"), "t002.ref.tdms", "no time: no 't_s'"),
    Bad(
        "tdms: other units than batch.yaml",
        lambda b: to_tdms(b / _ref(), unit="N"),
        "t002.ref.tdms",
        "channel 'fx' is in 'N' but batch.yaml says reference.units: mN",
        column="fx",
    ),
    Bad(
        "tdms: damaged file",
        lambda b: (to_tdms(b / _ref()), _truncate(b / "t002.ref.tdms", 30)),
        "t002.ref.tdms",
        "no data: an empty or damaged TDMS file (npTDMS: Last segment metadata is incomplete)",
    ),
    Bad(
        "tdms: not TDMS at all",
        lambda b: (to_tdms(b / _ref()), (b / "t002.ref.tdms").write_text("t_s,fx,fy,fz\n" * 9)),
        "t002.ref.tdms",
        "not a readable TDMS file (ValueError: File should either start with",
    ),
    Bad(
        "tdms: cut in the middle of its data",
        lambda b: (to_tdms(b / _ref()), _truncate(b / "t002.ref.tdms", 40_000)),
        "t002.ref.tdms",
        "samples, 'fx' has 2001 (a file cut short?)",
    ),
    Bad(
        "tdms: a glitch, located by sample number",
        lambda b: (set_cell(b / _ref(), 801, "fy", "30000"), to_tdms(b / _ref(), time="waveform")),
        "t002.ref.tdms",
        "glitch: fy = 30000 mN",
        line=800,
        column="fy",
    ),
    Bad(
        "tdms: a segment shorter than its channels",
        lambda b: _tdms_segment_short(b / _ref()),
        "t002.ref.tdms",
        "damaged file: a segment's data does not fit its channels (npTDMS: Data size",
    ),
    Bad(
        "tdms: waveform start of fz differs",
        lambda b: to_tdms(b / _ref(), time="waveform", properties={"fz": {"wf_start_offset": 1.5}}),
        "t002.ref.tdms",
        "waveform property 'wf_start_offset' is 1.5, 'fx' has 0.0",
        column="fz",
    ),
    Bad(
        "tdms: channel lengths differ",
        lambda b: to_tdms(b / _ref(), short="fz"),
        "t002.ref.tdms",
        "channel 'fz' has 2000 samples, 'fx' has 2001",
        column="fz",
    ),
]


@pytest.mark.parametrize("case", BAD, ids=[c.id for c in BAD])
def test_bad_input_is_set_aside_precisely(case: Bad, raw_dir: Path, lab_bench_a: Path, tmp_path: Path):
    # Given lab-bench-a with exactly one thing broken (plus an intact second batch when the
    # whole batch is expected to go)
    b = raw_dir / A
    case.mutate(b)
    if case.batch:
        copy_batch(lab_bench_a, raw_dir, "lab-bench-b")
    before = tree_hash(raw_dir)
    # When the folder is ingested
    result = run([raw_dir], tmp_path / "out")
    # Then a Problem names the file (and line/column) with the reason
    mine = [p for p in result.problems if p.batch_id == A]
    hits = [
        p
        for p in mine
        if Path(p.file).name == case.file
        and case.reason in p.reason
        and (case.line is None or p.line == case.line)
        and (case.column is None or p.column == case.column)
    ]
    assert hits, "\n".join(map(str, mine))
    outcome = next(o for o in result.batches if o.batch_id == A)
    out = tmp_path / "out"
    if case.batch:
        # ... the batch is set aside (a folder without trials.parquet), the other one goes on
        assert not outcome.accepted and A in result.set_aside
        assert result.accepted == ["lab-bench-b"]
        assert not (out / A / "trials.parquet").exists() and (out / A / "problems.json").exists()
    else:
        # ... only the broken trial is set aside; the others go through to the Parquet files
        assert outcome.accepted
        expected = list(case.accepted or [t for t in TRIALS if t not in case.trials])
        assert outcome.trials_accepted == expected
        assert outcome.trials_set_aside == sorted(case.trials)
        assert pd.read_parquet(out / A / "trials.parquet")["trial_id"].tolist() == expected
        assert sorted(pd.read_parquet(out / A / "fsr.parquet")["trial_id"].unique()) == expected
        assert sorted(pd.read_parquet(out / A / "ref.parquet")["trial_id"].unique()) == expected
        assert not {p.trial_id for p in mine} & set(expected)
    stored = [tuple(p.values()) for p in json.loads((out / A / "problems.json").read_text())]
    assert [tuple(p.to_dict().values()) for p in mine] == stored
    # ... and nothing under the raw folder changed
    assert tree_hash(raw_dir) == before


def test_many_bad_cells_are_summarised_but_all_set_aside(raw_dir, tmp_path):
    # Given a trial whose whole 'left' column is text
    f = raw_dir / A / _fsr()
    rows = [r.split(",") for r in lines_of(f)]
    write_lines(f, [",".join(rows[0])] + [",".join([r[0], "x", *r[2:]]) for r in rows[1:]])
    # When it is ingested
    result = run([raw_dir], tmp_path / "out")
    # Then a few lines are listed one by one, the rest in one summary line; t002 is set aside
    left = [p for p in result.problems if p.column == "left"]
    assert len(left) == MAX_PER_COLUMN + 1
    assert f"and {len(rows) - 1 - MAX_PER_COLUMN} more" in left[-1].reason
    assert result.batches[0].trials_accepted == ["t001", "t003"]


def test_a_file_the_os_will_not_read_is_a_located_problem(raw_dir, lab_bench_a, tmp_path, monkeypatch):
    # Given a second batch, and one stream file the OS refuses to read (tests run as root, where
    # chmod cannot make one: the refusal is injected where every read goes through, Path.open)
    copy_batch(lab_bench_a, raw_dir, "lab-bench-b")
    locked = raw_dir / A / _fsr()
    real_open = Path.open

    def guarded_open(self: Path, *args, **kwargs):
        if self == locked:
            raise PermissionError(13, "Permission denied", str(self))
        return real_open(self, *args, **kwargs)

    monkeypatch.setattr(Path, "open", guarded_open)
    # When the folder is ingested, and checked
    result = run([raw_dir], tmp_path / "out")
    checked = check.check_folders([raw_dir], IngestParams())
    # Then both name the file and the reason, and the other batch goes on
    for problems in (result.problems, checked):
        assert [p.reason for p in problems if Path(p.file) == locked] == ["cannot read: Permission denied"]
    assert "lab-bench-b" in result.accepted


def test_angles_are_read_as_their_numbers(raw_dir, tmp_path):
    # Given angles written "30°" and "-0" in trials.csv
    trials_csv = raw_dir / A / "trials.csv"
    set_cell(trials_csv, 2, "angle_deg", "30°")
    set_cell(trials_csv, 4, "angle_deg", "-0")
    # When ingested
    result = run([raw_dir], tmp_path / "out")
    # Then they are the angles 30 and 0 (not -0, which would name a folder "-0")
    assert result.accepted == [A]
    angles = pd.read_parquet(tmp_path / "out" / A / "trials.parquet")["angle_deg"].to_numpy()
    assert angles.tolist() == [30.0, 30.0, 0.0]
    assert not np.signbit(angles).any()


def test_a_last_row_cut_short_is_dropped_with_a_warning_and_the_trial_kept(raw_dir, tmp_path):
    # Given a stream whose recording lost power mid-row: the last row has 2 of its fields, no line break
    fsr = raw_dir / A / _fsr()
    rows = lines_of(fsr)
    fsr.write_text("\n".join(rows[:-1]) + "\n" + ",".join(rows[-1].split(",")[:2]))
    # When ingested
    result = run([raw_dir], tmp_path / "out")
    # Then the trial is kept without that row, and a warning names the file and line
    assert result.accepted == [A] and result.problems == []
    kept = pd.read_parquet(tmp_path / "out" / A / "fsr.parquet")
    assert (kept["trial_id"] == "t002").sum() == len(rows) - 2  # less the header and the cut row
    assert any(
        _fsr() in w and f"line {len(rows)}" in w and "cut short" in w for w in result.batches[0].warnings
    )
