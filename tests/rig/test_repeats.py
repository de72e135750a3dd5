"""One answer to "is this trial a copy?": `needlecue check` and the split stage set aside the same
trials, whatever file format or clock the copy has."""

from __future__ import annotations

import shutil
from pathlib import Path

from pipeline.config import IngestParams, ResampleParams, SplitParams
from pipeline.dataset import split
from pipeline.rig import repeats
from pipeline.rig.check import check_batches
from pipeline.rig.ingest import ingest_batches
from pipeline.signals import resample
from tests.rig.batches import gzip_file, lines_of, to_tdms, write_lines

LAB_BATCH = Path(__file__).parents[1] / "fixtures" / "rig-log" / "lab-bench-a"
TRIALS = ("t001", "t002", "t003")


def _copy(raw: Path, batch_id: str) -> Path:
    """lab-bench-a copied under another batch id."""
    b = shutil.copytree(LAB_BATCH, raw / batch_id)
    (b / "batch.yaml").write_text((b / "batch.yaml").read_text().replace("lab-bench-a", batch_id))
    return b


def _shift_times(batch: Path, trial: str) -> None:
    """Every timestamp of `trial`'s two streams 1 s later."""
    for name, step in ((f"{trial}.fsr.csv", 1000.0), (f"{trial}.ref.csv", 1.0)):
        rows = lines_of(batch / name)
        cells = [r.split(",") for r in rows[1:]]
        write_lines(
            batch / name, [rows[0], *(",".join([f"{float(c[0]) + step:.3f}", *c[1:]]) for c in cells)]
        )


def test_check_and_split_set_aside_the_same_copies(tmp_path: Path) -> None:
    # given: a batch; a copy with gzip-compressed files and TDMS reference streams; a copy whose t002
    # has every timestamp shifted and whose t003 was recorded again (its forces differ)
    raw = tmp_path / "raw"
    shutil.copytree(LAB_BATCH, raw / "lab-bench-a")
    formats = _copy(raw, "lab-bench-f")
    gzip_file(formats / "trials.csv")
    for t in TRIALS:
        gzip_file(formats / f"{t}.fsr.csv")
        to_tdms(formats / f"{t}.ref.csv")
    clocks = _copy(raw, "lab-bench-s")
    _shift_times(clocks, "t002")
    rows = lines_of(clocks / "t003.ref.csv")
    write_lines(clocks / "t003.ref.csv", [rows[0], *(r + "1" for r in rows[1:])])  # fz 6.8 -> 6.81
    # when: checked, and run through ingest, resample and split
    checked = check_batches([raw], IngestParams())
    said = repeats.repeats({(c.batch_id, t): h for c in checked for t, h in c.samples_sha256.items()})
    quiet = lambda _m: None  # noqa: E731
    ingest_batches([raw], tmp_path / "ingested", IngestParams(), log=quiet)
    resample.run(tmp_path / "ingested", tmp_path / "resampled", ResampleParams(), log=quiet)
    manifest = split.run(tmp_path / "resampled", tmp_path / "processed", SplitParams(), log=quiet)
    # then: the format copy repeats every trial, the shifted trial its original; lab-bench-s's t001
    # (a plain copy) repeats its original too, and its t003 (recorded again) repeats nothing
    expected = {("lab-bench-f", t): ("lab-bench-a", t) for t in TRIALS} | {
        ("lab-bench-s", t): ("lab-bench-a", t) for t in ("t001", "t002")
    }
    assert said == expected
    aside = {(s["batch_id"], s["trial_id"]): s["reason"] for s in manifest["set_aside"]}
    assert set(aside) == set(expected)
    for key, original in expected.items():
        assert aside[key] == repeats.reason(original)
