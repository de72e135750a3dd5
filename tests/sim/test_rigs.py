"""The family of rigs (`simulate.rig`): each member writes valid rig-log/1 batches that declare its
circuit, reads the way its circuit says, and aligns as well as the default; the default is the
simulator as it was."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
import yaml

from needlecue_runtime.frontend import conductance_us, volts_of
from pipeline.config import EffectScales, IngestParams, ResampleParams, SimulateParams
from pipeline.rig.format import BatchMeta
from pipeline.rig.ingest import ingest_batches
from pipeline.signals import resample
from pipeline.sim import physics, rig, rigs

SMALL = {
    "angles_deg": (15, 45),
    "train_batches": 1,
    "trials_per_angle": 3,
    "heldout_trials_per_angle": 0,
    "calibration_trials_per_angle": 0,
    "units": ("est-sim-001",),
    "new_units": (),
}


def _quiet(_: str) -> None:
    pass


@pytest.mark.parametrize("name", list(rigs.RIGS))
def test_every_member_writes_batches_that_declare_its_circuit_and_align(tmp_path, name):
    # Given a small layout of one member of the family
    p = SimulateParams(rig=name, **SMALL)
    rig.run(p, tmp_path / "sim", log=_quiet)
    batch = tmp_path / "sim" / "sim-tissue-1-est-sim-001"
    meta = BatchMeta.model_validate(yaml.safe_load((batch / "batch.yaml").read_text()))
    # Then its batch.yaml declares the member's circuit and ADC
    design = rigs.rig(name)
    assert meta.sensor.front_end == rigs.declared_front_end(design)
    assert meta.sensor.front_end.series_kohm == design.ri_kohm  # the FSR's R_i, as a lab would know it
    assert (meta.sensor.adc_bits, meta.sensor.vref_v) == (design.adc_bits, design.vref_v)
    # and, ingested and resampled with the defaults, every trial is kept (no gate tuned to one rig)
    ingest_batches([tmp_path / "sim"], tmp_path / "ing", IngestParams(), log=_quiet)
    rows = resample.run(tmp_path / "ing", tmp_path / "rs", ResampleParams(), log=_quiet).rows
    assert [r["status"] for r in rows] == ["ok"] * 6
    assert min(float(r["quality"]) for r in rows) > 0.7


@pytest.mark.parametrize("name", list(rigs.RIGS))
def test_the_declared_circuit_inverts_each_members_volts_to_its_fsr_conductance(name):
    # Given one unit of the member, loaded from nothing to 2 N (no hysteresis, drift or noise)
    est = rigs.rig(name)
    effects = EffectScales(hysteresis=0, drift=0, electrical_noise=0)
    load = np.tile(np.linspace(0.3, 2.0, 30)[:, None], (1, 3))
    v = physics.fsr_volts(load, np.zeros(30), est, effects, np.ones(3), np.random.default_rng(0))
    # When its volts are read back through the circuit the batch declares
    g = conductance_us(v, rigs.declared_front_end(est))
    # Then they give the FSR's own conductance (the law's, with the open FSR's), growing with the load
    law = load**est.law_exponent / (2 * est.rs_kohm_n) / (1 + np.exp(-(load - est.actuation_n) / 0.01))
    np.testing.assert_allclose(g, 1e3 * (law + 1.0 / est.r_open_kohm), rtol=1e-9)
    assert (np.diff(g[:, 0]) > 0).all()
    rising = np.diff(v[:, 0]) > 0
    assert rising.all() if getattr(est.front_end, "fsr_at", "supply") == "supply" else (~rising).all()


def test_the_default_rig_is_the_simulator_as_documented():
    est = rigs.rig(rigs.DEFAULT)
    assert est == physics.Estimator()
    # V = V+ / (1 + R / R_M) with V+ = 5 V, R_M = 10 kOhm (docs/physics.md §6), bit for bit
    r = np.geomspace(1.0, 1e4, 20)
    assert np.array_equal(volts_of(r, est.front_end), 5.0 / (1.0 + r / 10.0))


def test_a_batch_may_leave_its_circuit_undeclared(tmp_path):
    rig.run(SimulateParams(declare_front_end=False, **SMALL), tmp_path / "sim", log=_quiet)
    meta = yaml.safe_load((tmp_path / "sim" / "sim-tissue-1-est-sim-001" / "batch.yaml").read_text())
    assert "front_end" not in meta["sensor"] and meta["sensor"]["adc_bits"] == 10


def test_an_unknown_rig_names_the_family_before_anything_is_written(tmp_path):
    with pytest.raises(ValueError, match=r"simulate\.rig: no rig 'arduino'; the family is default, "):
        rig.run(SimulateParams(rig="arduino", **SMALL), tmp_path / "sim", log=_quiet)
    assert not (tmp_path / "sim").exists()


def test_members_differ_from_the_default_where_they_say_and_nowhere_else():
    base = physics.Estimator()
    for name, est in rigs.RIGS.items():
        changed = {f for f in base.__dataclass_fields__ if getattr(est, f) != getattr(base, f)}
        assert name == rigs.DEFAULT or changed, name
        assert not changed & {"azimuths_deg", "gains", "lateral_lever", "moving_mass_g", "n_fsr"}, name
    assert pd.Series([rigs.rig(n).front_end.circuit for n in rigs.RIGS]).nunique() == 2
