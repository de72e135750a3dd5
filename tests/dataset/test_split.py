"""The split: per angle, by trial, deterministic, held-out batches external only."""

from __future__ import annotations

import json

import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from needlecue_runtime.vocab import AXES, CALIBRATION, ID_COLUMNS, SPLITS
from pipeline.config import SplitParams
from pipeline.dataset import split as sp
from pipeline.dataset import split_plan
from pipeline.dataset.splits import SplitFiles, unit_roles
from pipeline.dataset.tables import write_table
from pipeline.dataset.trials import Trial
from tests.dataset.resampled import CHANNELS, files_of, make_input, trials_in, write_resampled


def test_every_trial_lands_in_exactly_one_split_and_held_out_batches_only_in_external(tmp_path):
    # Given two angles of training trials and a held-out batch per angle
    src = make_input(tmp_path / "in")
    # When the stage splits them
    manifest = sp.run(src, tmp_path / "out", SplitParams())
    # Then each angle folder has all four files, no trial twice, held-out trials only in external
    assert sorted(manifest["angles"]) == ["30", "45"]
    for angle in ("30", "45"):
        seen: set[tuple[str, str]] = set()
        for name in SPLITS:
            trials = trials_in(tmp_path / "out" / angle / f"{name}.parquet")
            assert trials, (angle, name)
            assert not trials & seen
            seen |= trials
            assert all(("heldout" in b) == (name == "external") for b, _ in trials)
            listed = {(d["batch_id"], d["trial_id"]) for d in manifest["angles"][angle]["splits"][name]}
            assert listed == trials
        assert len(seen) == 20
        # 16 internal trials: 5 % -> 1 in val, 10 % -> 2 in test (rounded), the rest train
        assert manifest["angles"][angle]["n_trials"] == {"train": 13, "val": 1, "test": 2, "external": 4}
    # And the samples of one trial are never split up: each split holds whole trials
    train = pq.read_table(tmp_path / "out/30/train.parquet").to_pandas()
    assert list(train.columns) == [*ID_COLUMNS, *CHANNELS, *AXES]
    assert manifest["angles"]["30"]["n_samples"]["train"] == len(train)
    assert manifest["rate_hz"] == 30.0 and manifest["set_aside"] == []
    # And every row carries its unit; with no calibration batch there is no calibration folder
    assert set(train.unit_id) == {"u1"}
    assert manifest["calibration"] == {} and not (tmp_path / "out" / "calibration").exists()


def test_two_runs_give_byte_identical_files(tmp_path):
    # Given the same input
    src = make_input(tmp_path / "in")
    # When split twice
    sp.run(src, tmp_path / "a", SplitParams())
    sp.run(src, tmp_path / "b", SplitParams())
    # Then every file is byte-identical, manifest included (a different seed gives another split)
    assert files_of(tmp_path / "a") == files_of(tmp_path / "b")
    sp.run(src, tmp_path / "c", SplitParams(seed=1))
    assert files_of(tmp_path / "a") != files_of(tmp_path / "c")


def test_more_data_at_45_leaves_angle_30_byte_identical(tmp_path):
    # Given a split, and the same data plus two more trials at 45 deg
    sp.run(make_input(tmp_path / "in1"), tmp_path / "a", SplitParams())
    sp.run(make_input(tmp_path / "in2", extra_45=2), tmp_path / "b", SplitParams())
    a, b = files_of(tmp_path / "a"), files_of(tmp_path / "b")
    # Then angle 30's files do not change at all, and angle 45 has the new trials
    at_30 = [k for k in a if k.startswith("30/")]
    assert len(at_30) == 5 and all(a[k] == b[k] for k in at_30)  # four splits and front_ends.json
    ma = json.loads(a["manifest.json"])
    mb = json.loads(b["manifest.json"])
    assert ma["angles"]["30"] == mb["angles"]["30"]
    assert sum(mb["angles"]["45"]["n_trials"].values()) == sum(ma["angles"]["45"]["n_trials"].values()) + 2


def test_a_batch_with_other_channels_is_set_aside_at_its_angle(tmp_path):
    # Given angle 30 with 16 trials on (fsr1..3) and 2 trials from a batch with 4 other channels
    src = make_input(tmp_path / "in")
    write_resampled(src, "lab-bench-a", {"t001": 30.0, "t002": 30.0}, channels=["l", "r", "t", "b"])
    # When split
    manifest = sp.run(src, tmp_path / "out", SplitParams())
    # Then the majority's channels are kept, the others set aside with a clear reason
    assert manifest["angles"]["30"]["channels"] == CHANNELS
    aside = manifest["set_aside"]
    assert [(s["batch_id"], s["trial_id"]) for s in aside] == [
        ("lab-bench-a", "t001"),
        ("lab-bench-a", "t002"),
    ]
    assert "differ from the channels" in aside[0]["reason"] and "angle 30" in aside[0]["reason"]
    for name in SPLITS:
        table = pq.read_table(tmp_path / "out" / "30" / f"{name}.parquet")
        assert "lab-bench-a" not in set(table.column("batch_id").to_pylist())
        assert table.column_names == [*ID_COLUMNS, *CHANNELS, *AXES]


def test_a_batch_copied_under_a_held_out_name_is_used_once(tmp_path):
    # Given a training cast copied, samples and all, under a held-out name, and one trial of it
    # copied inside the cast under another trial id
    src = make_input(tmp_path / "in")
    table = pq.read_table(src / "sim-tissue-1.parquet")
    copy = table.set_column(0, "batch_id", pa.array(["sim-heldout-copy"] * table.num_rows))
    write_table(copy, src / "sim-heldout-copy.parquet")
    meta = json.loads((src / "sim-tissue-1.json").read_text())
    (src / "sim-heldout-copy.json").write_text(json.dumps({**meta, "batch_id": "sim-heldout-copy"}))
    # When split
    manifest = sp.run(src, tmp_path / "out", SplitParams())
    # Then each recording is in one split of one angle only, and every repeat is set aside naming
    # the trial it repeats
    aside = {(s["batch_id"], s["trial_id"]): s["reason"] for s in manifest["set_aside"]}
    assert set(aside) == {("sim-tissue-1", t) for t in table.column("trial_id").unique().to_pylist()}
    assert aside["sim-tissue-1", "a30-t01"].startswith("the same samples as sim-heldout-copy/a30-t01")
    for angle in ("30", "45"):
        placed = [k for name in SPLITS for k in trials_in(tmp_path / "out" / angle / f"{name}.parquet")]
        assert len(placed) == len(set(placed))
        assert not {k for k in placed if k[0] == "sim-tissue-1"}
        assert {
            k for k in trials_in(tmp_path / "out" / angle / "external.parquet") if k[0] == "sim-heldout-copy"
        }


def test_a_trial_repeated_under_another_id_is_set_aside():
    # Given two trials with the same samples (ingest's hash of them) under different ids, and a third
    table = pa.table({"fsr1": [1.0, 2.0, 3.0]})
    t1, t2, t3 = (
        Trial("b", t, "30", ("fsr1",), table, samples_sha256=h)
        for t, h in [("t1", "h"), ("t2", "h"), ("t3", "k")]
    )
    # When repeats are dropped
    kept, aside = split_plan.drop_repeats([t3, t2, t1])
    # Then the first in (batch, trial) order stays
    assert [t.trial_id for t in kept] == ["t1", "t3"]
    assert [(s["trial_id"], s["reason"].split(":")[0]) for s in aside] == [("t2", "the same samples as b/t1")]


def test_resampled_batches_without_sample_hashes_are_refused_by_name(tmp_path):
    # Given a resampled batch written before the samples' hashes were carried
    src = make_input(tmp_path / "in")
    meta = json.loads((src / "sim-tissue-1.json").read_text())
    del meta["samples_sha256"]
    (src / "sim-tissue-1.json").write_text(json.dumps(meta))
    # When split, then the file is named
    with pytest.raises(ValueError, match=r"sim-tissue-1\.json: no samples_sha256"):
        sp.run(src, tmp_path / "out", SplitParams())


def test_empty_splits_are_written_with_the_schema(tmp_path):
    # Given an angle with 2 training trials and no held-out batch
    src = tmp_path / "in"
    src.mkdir()
    write_resampled(src, "lab-a", {"t1": 60.0, "t2": 60.0}, channels=["v"])
    # When split
    manifest = sp.run(src, tmp_path / "out", SplitParams())
    # Then all four files exist; the empty ones have the same columns and types
    full = pq.read_schema(tmp_path / "out/60/train.parquet")
    for name in ("val", "test", "external"):
        table = pq.read_table(tmp_path / "out/60" / f"{name}.parquet")
        assert table.num_rows == 0 and table.schema.equals(full)
    assert manifest["angles"]["60"]["n_trials"] == {"train": 2, "val": 0, "test": 0, "external": 0}


@pytest.mark.parametrize(
    ("n", "expected"),
    [
        (0, (0, 0, 0)),
        (1, (1, 0, 0)),
        (2, (2, 0, 0)),
        (3, (1, 1, 1)),
        (10, (8, 1, 1)),
        (20, (17, 1, 2)),
        (40, (34, 2, 4)),
    ],
)
def test_split_sizes_round_and_keep_one_in_val_and_test_from_three_trials(n, expected):
    # Given n internal trials and the paper's 5 % / 10 %, then the counts are as documented
    assert split_plan.split_sizes(n, 0.05, 0.10) == expected


def test_the_split_of_an_angle_depends_on_seed_and_angle_only():
    # Given the same trials listed in a different order
    keys = [("b1", f"t{k}") for k in range(12)]
    p = SplitParams()
    # Then the assignment is the same; another angle name shuffles differently
    assert split_plan.assign(keys, "30", p) == split_plan.assign(list(reversed(keys)), "30", p)
    assert any(
        split_plan.assign(keys, "30", p)[s] != split_plan.assign(keys, "45", p)[s] for s in ("train", "test")
    )


def _calibration(src, batch_id: str = "sim-calib-u-new", angles: tuple[float, ...] = (30.0, 45.0)) -> None:
    """A new unit's calibration batch: two trials at each angle."""
    trials = {f"a{a:g}-t{k:02d}": a for a in angles for k in (1, 2)}
    write_resampled(src, batch_id, trials, unit_id="u-new", purpose="calibration")


def test_calibration_trials_go_to_their_own_folder_only_even_when_named_held_out(tmp_path):
    # Given the usual input, a new unit's held-out batch at 30 deg, and its calibration batch
    # named like a held-out batch (it matches the external glob *heldout*)
    src = make_input(tmp_path / "in")
    write_resampled(src, "sim-heldout-30deg-u-new", {"a30-t01": 30.0, "a30-t02": 30.0}, unit_id="u-new")
    _calibration(src, "sim-heldout-calib-u-new")
    # When split
    manifest = sp.run(src, tmp_path / "out", SplitParams())
    out = tmp_path / "out"
    # Then the calibration trials are in calibration/<angle>.parquet and in no split of any angle
    calib = {("sim-heldout-calib-u-new", f"a{a}-t{k:02d}") for a in (30, 45) for k in (1, 2)}
    for angle in ("30", "45"):
        for name in SPLITS:
            assert not trials_in(out / angle / f"{name}.parquet") & calib
        assert trials_in(out / "calibration" / f"{angle}.parquet") == {
            t for t in calib if f"a{angle}-" in t[1]
        }
        # ... with the schema of the angle's split files, unit included
        table = pq.read_table(out / "calibration" / f"{angle}.parquet")
        assert table.schema.equals(pq.read_schema(out / angle / "train.parquet"))
        assert set(table.column("unit_id").to_pylist()) == {"u-new"}
    # And the manifest lists them with their unit, and says which units trained and which are new
    assert manifest["calibration"]["30"] == [
        {"batch_id": "sim-heldout-calib-u-new", "trial_id": f"a30-t0{k}", "unit_id": "u-new"} for k in (1, 2)
    ]
    assert manifest["units"] == {
        "u1": {
            "role": "training",
            "batches": ["sim-heldout-30deg", "sim-heldout-45deg", "sim-tissue-1", "sim-tissue-2"],
            "front_end": None,
        },
        "u-new": {
            "role": "new",
            "batches": ["sim-heldout-30deg-u-new", "sim-heldout-calib-u-new"],
            "front_end": None,
        },
    }
    assert unit_roles(out) == {"u1": "training", "u-new": "new"}  # what later stages read
    # And the new unit's held-out trials are external as usual
    assert ("sim-heldout-30deg-u-new", "a30-t01") in trials_in(out / "30" / "external.parquet")
    # And the later stages see only angle folders
    assert SplitFiles(out).angles() == ["30", "45"]


def test_adding_a_calibration_batch_leaves_the_angle_files_byte_identical(tmp_path):
    # Given a split, and the same input plus a new unit's calibration batch
    sp.run(make_input(tmp_path / "in1"), tmp_path / "a", SplitParams())
    src = make_input(tmp_path / "in2")
    _calibration(src)
    sp.run(src, tmp_path / "b", SplitParams())
    a, b = files_of(tmp_path / "a"), files_of(tmp_path / "b")
    # Then every angle file is byte-identical; only calibration files and the manifest are new
    angle_files = [k for k in a if k != "manifest.json"]
    assert len(angle_files) == 10 and all(a[k] == b[k] for k in angle_files)  # 4 splits + front_ends.json
    assert sorted(set(b) - set(a)) == [
        "calibration/30.parquet",
        "calibration/45.parquet",
        "calibration/front_ends.json",
    ]
    ma, mb = json.loads(a["manifest.json"]), json.loads(b["manifest.json"])
    assert ma["angles"] == mb["angles"]


def test_calibration_files_of_a_batch_that_is_gone_are_removed(tmp_path):
    # Given a split with a calibration batch at 30 and 45 deg
    src = make_input(tmp_path / "in")
    _calibration(src)
    out = tmp_path / "out"
    sp.run(src, out, SplitParams())
    # When it is replaced by one at 30 deg only, then removed
    (src / "sim-calib-u-new.parquet").unlink()
    _calibration(src, "sim-calib-u-new", angles=(30.0,))
    sp.run(src, out, SplitParams())
    # Then only 30 deg's calibration file is left, then none; the angle folders stay
    assert sorted(p.name for p in (out / "calibration").iterdir()) == ["30.parquet", "front_ends.json"]
    for f in ("sim-calib-u-new.parquet", "sim-calib-u-new.json"):
        (src / f).unlink()
    sp.run(src, out, SplitParams())
    assert not (out / "calibration").exists()
    assert sorted(p.name for p in out.iterdir()) == ["30", "45", "manifest.json"]


def test_a_calibration_trial_with_other_channels_is_set_aside(tmp_path):
    # Given a calibration batch whose channels differ from angle 30's
    src = make_input(tmp_path / "in")
    write_resampled(src, "calib-b", {"t1": 30.0}, channels=["v"], unit_id="u-b", purpose="calibration")
    # When split
    manifest = sp.run(src, tmp_path / "out", SplitParams())
    # Then it is set aside with the reason, and no calibration file is written
    assert [(s["batch_id"], s["trial_id"]) for s in manifest["set_aside"]] == [("calib-b", "t1")]
    assert "differ from the channels" in manifest["set_aside"][0]["reason"]
    assert manifest["calibration"] == {} and not (tmp_path / "out" / "calibration").exists()


def test_angles_to_train_without_data_stop_the_split_with_the_params_line_to_set(tmp_path):
    # Given trials at 30 and 45° only, and models to train at 15, 30 and 45°
    src = make_input(tmp_path / "in")
    # When the split runs / Then one message names the angle, the angles found and what to set,
    # before anything is written
    with pytest.raises(
        ValueError, match=r"train\.angles lists 15°.*training trials: 30°, 45°.*`train\.angles: \[30, 45\]`"
    ):
        sp.run(src, tmp_path / "out", SplitParams(), trained=(15.0, 30.0, 45.0))
    assert not (tmp_path / "out").exists()
    # and with the angles of the data it splits as before
    assert sorted(sp.run(src, tmp_path / "out", SplitParams(), trained=(30.0, 45.0))["angles"]) == [
        "30",
        "45",
    ]


def test_an_angle_whose_batches_record_different_axes_trains_on_the_axes_all_of_them_record(tmp_path):
    # Given: at 30 deg, the training casts record fx, fy, fz and the held-out batch fz alone (a load
    # cell); 45 deg is recorded on all three axes throughout; and a calibration batch with fy and fz
    src = make_input(tmp_path / "in")
    write_resampled(src, "sim-heldout-30deg", {f"a30-t{k:02d}": 30.0 for k in range(1, 5)}, axes=("fz",))
    write_resampled(
        src,
        "calib-u-new",
        {"a30-t01": 30.0, "a45-t01": 45.0},
        unit_id="u-new",
        purpose=CALIBRATION,
        axes=("fy", "fz"),
    )
    logged: list[str] = []
    # When: split
    manifest = sp.run(src, tmp_path / "out", SplitParams(), log=logged.append)
    out = tmp_path / "out"
    # Then: every 30 deg file holds fz alone (nothing stands in for fx or fy), 45 deg keeps all three
    for name in SPLITS:
        assert [a for a in AXES if a in pq.read_schema(out / "30" / f"{name}.parquet").names] == ["fz"]
        assert [a for a in AXES if a in pq.read_schema(out / "45" / f"{name}.parquet").names] == list(AXES)
    # And: no trial is set aside for it; the manifest and the log name the axes left out, and where
    assert not manifest["set_aside"]
    assert manifest["angles"]["30"]["axes"] == ["fz"]
    assert manifest["angles"]["30"]["axes_left_out"] == {
        "sim-tissue-1": ["fx", "fy"],
        "sim-tissue-2": ["fx", "fy"],
    }
    assert "axes" not in manifest["angles"]["45"] and "axes_left_out" not in manifest["angles"]["45"]
    assert any("angle 30: sim-tissue-1 records fx, fy too" in line for line in logged)
    # And: a calibration trial keeps the axes both it and its angle's models have
    assert [a for a in AXES if a in pq.read_schema(out / "calibration" / "30.parquet").names] == ["fz"]
    assert [a for a in AXES if a in pq.read_schema(out / "calibration" / "45.parquet").names] == ["fy", "fz"]
    assert manifest["calibration_axes_left_out"] == {"30": {"calib-u-new": ["fy"]}}


def test_trials_sharing_no_axis_with_their_angle_are_set_aside_saying_which_axes(tmp_path):
    # Given: at 30 deg the two training casts record fz, the held-out batch fx alone
    src = make_input(tmp_path / "in")
    for b in (1, 2):
        trials = {f"a30-t{k:02d}": 30.0 for k in range(1, 9)}
        write_resampled(src, f"sim-tissue-{b}", trials, axes=("fz",))
    write_resampled(src, "sim-heldout-30deg", {f"a30-t{k:02d}": 30.0 for k in range(1, 5)}, axes=("fx",))
    # When: split
    manifest = sp.run(src, tmp_path / "out", SplitParams())
    # Then: the majority's axis is kept, and the held-out trials are set aside with the reason
    assert manifest["angles"]["30"]["axes"] == ["fz"]
    aside = [s for s in manifest["set_aside"] if s["batch_id"] == "sim-heldout-30deg"]
    assert len(aside) == 4
    assert (
        aside[0]["reason"]
        == "its reference records ['fx'], no force axis of the ['fz'] of the trials at angle 30"
    )
