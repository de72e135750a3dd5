"""The rig simulator writes deterministic rig-log/1 folders."""

from __future__ import annotations

import hashlib
import json
from fnmatch import fnmatchcase

import pandas as pd
import pytest
import yaml

from pipeline.config import IngestParams, ResampleParams, SimulateParams
from pipeline.rig.format import BatchMeta
from pipeline.signals.one_batch import read_batch
from pipeline.sim import rig
from tests.helpers import tree_hash

SMALL = SimulateParams(
    angles_deg=(15, 45),
    train_batches=1,
    trials_per_angle=2,
    heldout_trials_per_angle=1,
    units=("est-sim-001",),
    new_units=(),
)
# two training units, one new unit with its calibration batch
LAYOUT = SimulateParams(
    angles_deg=(15, 45),
    train_batches=2,
    trials_per_angle=2,
    heldout_trials_per_angle=3,
    calibration_trials_per_angle=1,
    units=("u-a", "u-b"),
    new_units=("u-new",),
)


def test_writes_one_training_cast_and_a_heldout_batch_per_angle(tmp_path):
    # When the simulator runs on a small plan with one unit
    ids = rig.run(SMALL, tmp_path / "sim")
    # Then it writes a training cast and one held-out batch per angle
    assert ids == ["sim-tissue-1-est-sim-001", "sim-heldout-15deg", "sim-heldout-45deg"]
    batch = tmp_path / "sim" / "sim-tissue-1-est-sim-001"
    meta = BatchMeta.model_validate(yaml.safe_load((batch / "batch.yaml").read_text()))
    assert meta.batch_id == "sim-tissue-1-est-sim-001" and meta.sensor.units == "counts"
    assert meta.sensor.unit_id == "est-sim-001" and meta.purpose == "training"
    trials = pd.read_csv(batch / "trials.csv")
    assert sorted(trials.angle_deg.unique()) == [15, 45]
    # And every trial has both streams in the format's columns, counts inside the ADC range
    for trial_id in trials.trial_id:
        fsr = pd.read_csv(batch / f"{trial_id}.fsr.csv")
        ref = pd.read_csv(batch / f"{trial_id}.ref.csv")
        assert list(fsr.columns) == ["t_ms", "fsr1", "fsr2", "fsr3"]
        assert list(ref.columns) == ["t_s", "fx", "fy", "fz"]
        assert fsr[["fsr1", "fsr2", "fsr3"]].stack().between(0, 1023).all()
        assert fsr.t_ms.is_monotonic_increasing and ref.t_s.is_monotonic_increasing


def test_same_params_same_bytes(tmp_path):
    rig.run(SMALL, tmp_path / "a")
    rig.run(SMALL, tmp_path / "b")
    assert tree_hash(tmp_path / "a") == tree_hash(tmp_path / "b")
    rig.run(SMALL.model_copy(update={"seed": 1}), tmp_path / "c")
    assert tree_hash(tmp_path / "a") != tree_hash(tmp_path / "c")


def test_disabled_writes_only_the_manifest(tmp_path):
    assert rig.run(SMALL.model_copy(update={"enabled": False}), tmp_path / "sim") == []
    assert [p.name for p in (tmp_path / "sim").iterdir()] == [rig.MANIFEST]


def test_refuses_to_clear_a_folder_it_did_not_write(tmp_path):
    # Given a folder holding someone's data
    (tmp_path / "lab").mkdir()
    (tmp_path / "lab" / "precious.csv").write_text("1,2,3\n")
    # Then the simulator will not write into it, and leaves it alone
    with pytest.raises(FileExistsError, match="not written by the simulator"):
        rig.run(SMALL, tmp_path / "lab")
    assert (tmp_path / "lab" / "precious.csv").read_text() == "1,2,3\n"


def test_layout_names_units_roles_and_purposes():
    # When the layout with two training units and one new unit is planned
    plans = rig.plan_batches(LAYOUT)
    got = [(b.batch_id, b.unit_id, b.purpose, b.role, b.trials_per_angle) for b in plans]
    # Then every cast is recorded by every training unit, each held-out angle by a training unit
    # (in turn) and by the new unit, and the new unit has a calibration batch at every angle
    assert got == [
        ("sim-tissue-1-u-a", "u-a", "training", "training", 2),
        ("sim-tissue-1-u-b", "u-b", "training", "training", 2),
        ("sim-tissue-2-u-a", "u-a", "training", "training", 2),
        ("sim-tissue-2-u-b", "u-b", "training", "training", 2),
        ("sim-heldout-15deg", "u-a", "training", "held-out", 3),
        ("sim-heldout-45deg", "u-b", "training", "held-out", 3),
        ("sim-heldout-15deg-u-new", "u-new", "training", "new-unit", 3),
        ("sim-heldout-45deg-u-new", "u-new", "training", "new-unit", 3),
        ("sim-calib-u-new", "u-new", "calibration", "calibration", 1),
    ]
    assert [b.angles_deg for b in plans if b.role != "training"] == [(15,), (45,), (15,), (45,), (15, 45)]
    # And the units recording one cast share it; every other batch has a cast of its own
    assert [b.cast for b in plans] == [1, 1, 2, 2, 3, 4, 5, 6, 7]
    assert len({b.number for b in plans}) == len(plans)
    # And every held-out batch matches the default external glob, the calibration batch does not
    assert all(fnmatchcase(b.batch_id, "*heldout*") == (b.role in ("held-out", "new-unit")) for b in plans)


def test_default_layout_trial_counts_per_angle():
    # Given the default params (3 casts x 3 training units x 3 trials, 21 held-out, 1 calibration)
    plans = rig.plan_batches(SimulateParams())
    per_angle: dict[str, int] = {}
    for b in plans:
        per_angle[b.role] = per_angle.get(b.role, 0) + b.trials_per_angle * len(b.angles_deg)
    # Then each of the 6 angles has 27 training, 21 same-unit held-out, 21 new-unit held-out trials
    # and one calibration trial
    assert {role: n / 6 for role, n in per_angle.items()} == {
        "training": 27,
        "held-out": 21,
        "new-unit": 21,
        "calibration": 1,
    }


def test_units_of_one_cast_share_its_stiffness_and_casts_differ():
    plans = rig.plan_batches(LAYOUT)
    by_cast = {b.cast: rig.cast_scale(LAYOUT, b.cast) for b in plans}
    assert len(set(by_cast.values())) == len(by_cast)  # one scale per cast, all different
    off = LAYOUT.model_copy(update={"effects": LAYOUT.effects.model_copy(update={"batch_variation": 0})})
    assert {rig.cast_scale(off, c) for c in by_cast} == {1.0}


def test_batch_yaml_and_manifest_name_the_unit_and_purpose(tmp_path):
    # When the layout is simulated
    ids = rig.run(LAYOUT, tmp_path / "sim")
    # Then every batch.yaml names its unit, purpose and role
    metas = {b: yaml.safe_load((tmp_path / "sim" / b / "batch.yaml").read_text()) for b in ids}
    calib = metas["sim-calib-u-new"]
    assert calib["purpose"] == "calibration" and calib["sensor"]["unit_id"] == "u-new"
    assert calib["simulator"] == {"seed": LAYOUT.seed, "role": "calibration", "rig": "default"}
    assert metas["sim-heldout-45deg-u-new"]["simulator"]["role"] == "new-unit"
    assert metas["sim-heldout-45deg"]["simulator"]["role"] == "held-out"
    assert metas["sim-heldout-45deg"]["sensor"]["unit_id"] == "u-b"
    assert {m["sensor"]["unit_id"] for b, m in metas.items() if b.startswith("sim-tissue-")} == {"u-a", "u-b"}
    assert all(BatchMeta.model_validate(m).purpose == m["purpose"] for m in metas.values())
    # And the calibration batch has its trials at every angle
    trials = pd.read_csv(tmp_path / "sim" / "sim-calib-u-new" / "trials.csv")
    assert sorted(trials.angle_deg) == [15, 45]
    # And the manifest lists each unit as drawn: the same numbers as drawing it again, all different
    units = json.loads((tmp_path / "sim" / rig.MANIFEST).read_text())["units"]
    assert sorted(units) == ["u-a", "u-b", "u-new"]
    assert units["u-a"] == rig.unit_summary(rig.draw_unit(LAYOUT, "u-a"))
    assert len({tuple(u["gains"]) for u in units.values()}) == 3
    assert set(units["u-new"]) == {"gains", "preloads_n", "azimuths_deg", "drift_per_decade"}


@pytest.mark.parametrize(
    ("update", "reason"),
    [
        ({"units": ()}, "at least one training unit"),
        ({"units": ("u1", "u1")}, "twice"),
        ({"new_units": ("bad unit",)}, "id pattern"),
        ({"units": ("u1",), "new_units": ("u1",)}, "disjoint"),
    ],
    ids=["no units", "a unit twice", "bad id", "new unit also training"],
)
def test_bad_unit_lists_fail_loudly(update, reason):
    with pytest.raises(ValueError, match=reason):
        SimulateParams.model_validate({**SMALL.model_dump(), **update})


def test_a_unit_id_too_long_for_its_batch_ids_is_refused_before_writing(tmp_path):
    params = SMALL.model_copy(update={"units": ("u" * 60,)})
    with pytest.raises(ValueError, match="shorter unit ids"):
        rig.run(params, tmp_path / "sim")
    assert not (tmp_path / "sim").exists()


def test_a_new_calibration_batch_by_a_new_unit(tmp_path):
    # When a lab-style calibration batch is added, recorded by a unit of its own
    rig.write_new_batch(
        SMALL, tmp_path / "raw", "calib-x", (15.0,), 1, unit_id="est-x", purpose="calibration"
    )
    meta = yaml.safe_load((tmp_path / "raw" / "calib-x" / "batch.yaml").read_text())
    # Then its batch.yaml says so; the default is a training batch by the first training unit
    assert (meta["purpose"], meta["sensor"]["unit_id"], meta["simulator"]["role"]) == (
        "calibration",
        "est-x",
        "calibration",
    )
    rig.write_new_batch(SMALL, tmp_path / "raw", "cast-y", (15.0,), 1)
    meta = yaml.safe_load((tmp_path / "raw" / "cast-y" / "batch.yaml").read_text())
    assert (meta["purpose"], meta["sensor"]["unit_id"]) == ("training", "est-sim-001")
    # And a bad purpose or unit id is refused before anything is written
    with pytest.raises(ValueError, match="purpose 'calib'"):
        rig.write_new_batch(SMALL, tmp_path / "raw", "z", (15.0,), 1, purpose="calib")
    with pytest.raises(ValueError, match="unit id"):
        rig.write_new_batch(SMALL, tmp_path / "raw", "z", (15.0,), 1, unit_id="a unit")
    assert not (tmp_path / "raw" / "z").exists()


# The SMALL run's files, hashed as `_tree_digest` does, by the simulator of git HEAD 4c1f45c (before
# `simulate.reference_axes`): run in a copy of that commit (`git archive`), not guessed.
SMALL_BEFORE_REFERENCE_AXES = "6f722e85a9c9268b60b4dcd50c91e625052766592a27856f243826eb3798a62b"


def _tree_digest(root) -> str:
    return hashlib.sha256(json.dumps(tree_hash(root), sort_keys=True).encode()).hexdigest()


def test_the_default_reference_axes_write_the_same_bytes_as_before_they_existed(tmp_path):
    # Given the default reference_axes (all three), said or not
    said = SMALL.model_copy(update={"reference_axes": ("fx", "fy", "fz")})
    # When the simulator runs
    for name, params in (("default", SMALL), ("said", said)):
        rig.run(params, tmp_path / name)
        # Then every file, manifest included, is byte for byte what the simulator wrote before
        assert _tree_digest(tmp_path / name) == SMALL_BEFORE_REFERENCE_AXES
    assert (
        "axes"
        not in yaml.safe_load((tmp_path / "said" / "sim-heldout-15deg" / "batch.yaml").read_text())[
            "reference"
        ]
    )


def test_a_one_axis_reference_writes_t_s_and_fz_and_declares_it(tmp_path):
    # Given simulate.reference_axes [fz] (a one-axis load cell)
    params = SMALL.model_copy(update={"reference_axes": ("fz",)})
    # When the simulator runs, and the default one beside it
    ids = rig.run(params, tmp_path / "one")
    rig.run(SMALL, tmp_path / "three")
    # Then each batch.yaml declares reference.axes [fz] and each reference file holds t_s and fz only,
    # the same fz as the three-axis run's; the estimator streams are the same bytes
    for b in ids:
        meta = BatchMeta.model_validate(yaml.safe_load((tmp_path / "one" / b / "batch.yaml").read_text()))
        assert meta.reference.axes == ["fz"]
        for ref in sorted((tmp_path / "one" / b).glob("*.ref.csv")):
            one = pd.read_csv(ref)
            assert list(one.columns) == ["t_s", "fz"]
            three = pd.read_csv(tmp_path / "three" / b / ref.name)
            pd.testing.assert_frame_equal(one, three[["t_s", "fz"]])
        for fsr in (tmp_path / "one" / b).glob("*.fsr.csv"):
            assert fsr.read_bytes() == (tmp_path / "three" / b / fsr.name).read_bytes()
    # And the manifest records the axes
    manifest = json.loads((tmp_path / "one" / rig.MANIFEST).read_text())
    assert manifest["params"]["reference_axes"] == ["fz"]


@pytest.mark.parametrize(
    ("axes", "reason"),
    [
        ((), "at least one"),
        (("fz", "fz"), "at most once"),
        (("fz", "tz"), "Input should be 'fx', 'fy' or 'fz'"),
    ],
    ids=["none", "twice", "not an axis"],
)
def test_bad_reference_axes_fail_loudly(axes, reason):
    with pytest.raises(ValueError, match=reason):
        SimulateParams.model_validate({**SMALL.model_dump(), "reference_axes": axes})


def test_a_simulated_one_axis_batch_is_ingested_and_resampled_with_fz_alone(tmp_path):
    # Given a simulated batch whose reference records fz alone
    params = SMALL.model_copy(update={"reference_axes": ("fz",)})
    rig.write_new_batch(params, tmp_path / "raw", "load-cell-1", (30.0,), 2)
    # When it is read and resampled as the pipeline does
    batch = read_batch(tmp_path / "raw" / "load-cell-1", IngestParams(), ResampleParams())
    # Then nothing is set aside, and the rows carry the one force column
    assert batch.problems == [] and batch.set_aside == []
    assert [c for c in ("fx", "fy", "fz") if c in batch.rows.columns] == ["fz"]
    assert sorted(batch.rows.trial_id.unique()) == ["a30-t01", "a30-t02"]
