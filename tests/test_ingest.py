"""ingest: a good hand-made batch goes through; every kind of bad input is set aside precisely."""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pandas as pd
import pytest

from pipeline import ingest
from pipeline.config import IngestParams
from pipeline.riglog import BatchMeta
from tests.helpers import tree_hash

A = "lab-bench-a"
TRIALS = ["t001", "t002", "t003"]
CHANNELS = ["left", "right", "top", "bottom"]


# --------------------------------------------------------------------------- helpers


def run(roots: list[Path], out: Path, params: IngestParams | None = None) -> ingest.IngestResult:
    return ingest.ingest_batches(roots, out, params or IngestParams(), log=lambda _: None)


def copy_batch(src: Path, root: Path, name: str) -> Path:
    """A copy of batch `src` under `root`, renamed (batch_id follows the folder name)."""
    dst = root / name
    shutil.copytree(src, dst)
    meta = dst / "batch.yaml"
    meta.write_text(meta.read_text().replace(f"batch_id: {src.name}", f"batch_id: {name}"))
    return dst


def lines_of(path: Path) -> list[str]:
    return path.read_text().splitlines()


def write_lines(path: Path, lines: list[str]) -> None:
    path.write_text("\n".join(lines) + "\n")


def set_cell(path: Path, line: int, column: str, value: str) -> None:
    """Replace one CSV cell (line 1 = header)."""
    rows = lines_of(path)
    col = rows[0].split(",").index(column)
    fields = rows[line - 1].split(",")
    fields[col] = value
    rows[line - 1] = ",".join(fields)
    write_lines(path, rows)


def cell(path: Path, line: int, column: str) -> str:
    rows = lines_of(path)
    return rows[line - 1].split(",")[rows[0].split(",").index(column)]


def drop_column(path: Path, column: str) -> None:
    rows = [r.split(",") for r in lines_of(path)]
    col = rows[0].index(column)
    write_lines(path, [",".join(f for i, f in enumerate(r) if i != col) for r in rows])


def replace_in(path: Path, old: str, new: str) -> None:
    text = path.read_text()
    assert old in text
    path.write_text(text.replace(old, new, 1))


def to_counts(b: Path) -> None:
    """Turn the volts batch into a 10-bit counts batch (values rounded to integer counts)."""
    replace_in(b / "batch.yaml", "units: volts", "units: counts\n  adc_bits: 10\n  vref_v: 5.0")
    for f in sorted(b.glob("*.fsr.csv")):
        rows = [r.split(",") for r in lines_of(f)]
        write_lines(
            f,
            [",".join(rows[0])]
            + [",".join([r[0], *(str(round(float(v) / 5.0 * 1023)) for v in r[1:])]) for r in rows[1:]],
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
        "missing trials.csv",
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
    Bad("trial without its ref file", lambda b: (b / _ref()).unlink(), _ref(), "is missing"),
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
    assert len(left) == ingest.MAX_PER_COLUMN + 1
    assert f"and {len(rows) - 1 - ingest.MAX_PER_COLUMN} more" in left[-1].reason
    assert result.batches[0].trials_accepted == ["t001", "t003"]


# --------------------------------------------------------------------------- folders and roots


def test_duplicate_batch_id_in_second_root_is_set_aside(raw_dir, lab_bench_a, tmp_path):
    # Given the same batch in the raw and the simulated folder
    sim = tmp_path / "sim"
    shutil.copytree(lab_bench_a, sim / A)
    # When both are ingested
    result = run([raw_dir, sim], tmp_path / "out")
    # Then the raw copy is used and the second is set aside with a Problem naming it
    assert result.accepted == [A]
    dup = [b for b in result.batches if b.action == "duplicate"]
    assert len(dup) == 1 and dup[0].source_dir == sim / A
    assert "already read from" in dup[0].problems[0].reason and dup[0].problems[0].file == str(sim / A)
    assert json.loads((tmp_path / "out" / A / "batch.json").read_text())["source_dir"] == str(raw_dir / A)


def test_batch_folder_with_an_invalid_name_is_set_aside(raw_dir, lab_bench_a, tmp_path):
    # Given a batch folder (and batch_id) with a space in its name
    copy_batch(lab_bench_a, raw_dir, "lab bench")
    # When ingested / Then it is set aside for its id, the other batch goes through
    result = run([raw_dir], tmp_path / "out")
    assert result.accepted == [A] and result.set_aside == ["lab bench"]
    assert "does not match" in result.problems[0].reason


def test_missing_folders_have_no_batches(tmp_path):
    # Given neither input folder exists / When ingested / Then nothing happens, no error
    result = run([tmp_path / "nope", tmp_path / "nada"], tmp_path / "out")
    assert result.batches == [] and list((tmp_path / "out").iterdir()) == []


def test_output_inside_an_input_folder_is_refused(raw_dir):
    # Given an output folder under the raw folder / When ingest starts / Then it refuses
    with pytest.raises(ValueError, match="overlaps"):
        run([raw_dir], raw_dir / "ingested")


# --------------------------------------------------------------------------- incremental


def test_unchanged_batch_is_reused_without_parsing(raw_dir, lab_bench_a, tmp_path, monkeypatch):
    # Given a first ingest
    out = tmp_path / "out"
    first = run([raw_dir], out)
    assert first.parsed == [A]
    stored = tree_hash(out)

    # When it runs again with parsing made impossible
    def no_parse(*_a, **_k):
        raise AssertionError("an unchanged batch was parsed")

    with monkeypatch.context() as m:
        m.setattr(ingest, "parse_batch", no_parse)
        second = run([raw_dir], out)
    # Then the batch is reused and its outputs are untouched
    assert second.reused == [A] and second.parsed == []
    assert second.batches[0].trials_accepted == TRIALS
    assert tree_hash(out) == stored
    # When a second batch arrives, only that one is parsed
    copy_batch(lab_bench_a, raw_dir, "lab-bench-b")
    third = run([raw_dir], out)
    assert third.parsed == ["lab-bench-b"] and third.reused == [A]
    # When a byte of a file changes, that batch is parsed again
    set_cell(raw_dir / "lab-bench-b" / "t001.ref.csv", 5, "fx", "1.5")
    fourth = run([raw_dir], out)
    assert fourth.parsed == ["lab-bench-b"] and fourth.reused == [A]
    # When the ingest params change, everything is parsed again
    assert run([raw_dir], out, IngestParams(min_samples=20)).parsed == [A, "lab-bench-b"]
    # When a batch is removed from the raw folder, its output goes too
    shutil.rmtree(raw_dir / A)
    fifth = run([raw_dir], out, IngestParams(min_samples=20))
    assert fifth.removed == [A] and not (out / A).exists() and fifth.reused == ["lab-bench-b"]


def test_set_aside_batch_is_not_parsed_again_either(raw_dir, tmp_path, monkeypatch):
    # Given a batch set aside for a bad batch.yaml
    (raw_dir / A / "batch.yaml").write_text("format: [\n")
    out = tmp_path / "out"
    assert run([raw_dir], out).set_aside == [A]
    assert sorted(p.name for p in (out / A).iterdir()) == ["fingerprint.json", "problems.json"]
    # When ingest runs again / Then it is reused, problems and all
    monkeypatch.setattr(ingest, "parse_batch", lambda *a, **k: pytest.fail("parsed"))
    again = run([raw_dir], out)
    assert again.reused == [A] and again.set_aside == [A] and "not valid YAML" in again.problems[0].reason


def test_crash_while_writing_leaves_no_matching_fingerprint(raw_dir, tmp_path, monkeypatch):
    # Given an ingested batch that then changes
    out = tmp_path / "out"
    run([raw_dir], out)
    set_cell(raw_dir / A / "t001.fsr.csv", 5, "left", "0.5")
    # When writing its new outputs fails half way
    with monkeypatch.context() as m:
        m.setattr(ingest, "_write_parquet", lambda *a, **k: (_ for _ in ()).throw(OSError("disk full")))
        with pytest.raises(OSError):
            run([raw_dir], out)
    # Then the next run parses it again (no stale fingerprint matches) and writes the new value
    again = run([raw_dir], out)
    assert again.parsed == [A]
    fsr = pd.read_parquet(out / A / "fsr.parquet")
    assert fsr.loc[fsr.trial_id == "t001", "left"].iloc[3] == 0.5
    assert sorted(p.name for p in out.iterdir()) == [A]


# --------------------------------------------------------------------------- entry point, reports, check


def _params(tmp_path: Path, enabled: bool) -> Path:
    p = tmp_path / "params.yaml"
    p.write_text(f"simulate:\n  enabled: {str(enabled).lower()}\ningest:\n  min_samples: 10\n")
    return p


def test_simulate_disabled_reads_only_raw(raw_dir, lab_bench_a, tmp_path):
    # Given a raw and a simulated batch, and simulate.enabled: false
    copy_batch(lab_bench_a, tmp_path / "sim", "sim-b")
    out = tmp_path / "out"
    # When the stage runs
    ingest.main(raw_dir, tmp_path / "sim", out, tmp_path / "reports", _params(tmp_path, False))
    # Then only the raw batch is ingested
    assert sorted(p.name for p in out.iterdir()) == [A]


def test_stage_writes_reports_and_data_docs(raw_dir, lab_bench_a, tmp_path, capsys, monkeypatch):
    # Given a good raw batch and a simulated batch with one bad cell, simulate enabled, and
    # relative paths as dvc.yaml passes them
    sim_b = copy_batch(lab_bench_a, tmp_path / "sim", "sim-b")
    set_cell(sim_b / "t003.ref.csv", 12, "fy", "oops")
    _params(tmp_path, True)
    monkeypatch.chdir(tmp_path)
    reports = Path("reports")
    # When the stage runs
    ingest.main(Path("raw"), Path("sim"), Path("out"), reports, Path("params.yaml"))
    # Then both batches are ingested, and the reports say what was set aside and where
    assert sorted(p.name for p in Path("out").iterdir()) == [A, "sim-b"]
    quarantine = json.loads((reports / "quarantine.json").read_text())
    assert quarantine == [
        {
            "batch_id": "sim-b",
            "trial_id": "t003",
            "file": "sim/sim-b/t003.ref.csv",
            "line": 12,
            "column": "fy",
            "reason": "text 'oops' in a number column",
        }
    ]
    line = "sim/sim-b/t003.ref.csv:12 column 'fy': text 'oops' in a number column"
    assert line in (reports / "summary.md").read_text()
    assert line in capsys.readouterr().err
    assert sorted(p.name for p in (reports / "gx").iterdir()) == [f"{A}.json", "sim-b.json"]
    docs = reports / "data_docs"
    assert (docs / "index.html").is_file()
    assert len(list((docs / "validations").rglob("*.html"))) == 8  # 2 batches x 4 frames
    # When it runs again with nothing changed
    ingest.main(Path("raw"), Path("sim"), Path("out"), reports, Path("params.yaml"))
    # Then both batches are reused and the reports (Data Docs included) are complete again
    assert f"{A}: reused" in capsys.readouterr().err
    assert json.loads((reports / "quarantine.json").read_text()) == quarantine
    assert len(list((docs / "validations").rglob("*.html"))) == 8


def test_check_folders_reports_problems_and_writes_nothing(raw_dir, lab_bench_a, tmp_path):
    # Given a good fixture and a broken copy
    bad = copy_batch(lab_bench_a, raw_dir, "lab-bench-b")
    drop_column(bad / "t001.fsr.csv", "left")
    before = tree_hash(tmp_path)
    # When they are checked (as a folder of batches and as one batch folder)
    problems = ingest.check_folders([raw_dir], IngestParams())
    single = ingest.check_folders([lab_bench_a], IngestParams())
    # Then exactly the broken file is reported, and nothing was written anywhere
    assert [(p.batch_id, Path(p.file).name, p.column) for p in problems] == [
        ("lab-bench-b", "t001.fsr.csv", "left")
    ]
    assert single == []
    assert tree_hash(tmp_path) == before
