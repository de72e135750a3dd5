"""The estimator's front end (batch.yaml `sensor.front_end`): each circuit's volts invert to the
FSR's resistance, and a declared front end is kept through ingest."""

from __future__ import annotations

import json

import numpy as np
import pytest

from needlecue_runtime.frontend import (
    Divider,
    Transimpedance,
    Undeclared,
    conductance_us,
    conductance_us_of_frame,
    is_declared,
    volts_of,
)
from pipeline.rig.format import SensorMeta
from tests.rig.batches import A, replace_in, run

CIRCUITS = [
    Divider(circuit="divider", supply_v=5.0, fixed_kohm=10.0),
    Divider(circuit="divider", supply_v=3.3, fixed_kohm=47.0, fsr_at="ground", series_kohm=0.5),
    Transimpedance(circuit="transimpedance", drive_v=1.0, feedback_kohm=47.0, offset_v=0.1),
]


@pytest.mark.parametrize("fe", CIRCUITS, ids=lambda fe: f"{fe.circuit}-{getattr(fe, 'fsr_at', '')}")
def test_volts_invert_to_the_fsr_conductance(fe):
    # Given FSR resistances from a loaded FSR (2 kOhm) to a nearly open one (2 MOhm)
    r = np.geomspace(2.0, 2000.0, 50)
    # When they are read through the circuit and inverted
    g = conductance_us(volts_of(r, fe), fe)
    # Then the conductance is the FSR's own, its series resistance taken out
    np.testing.assert_allclose(g, 1e3 / r, rtol=1e-9)


def test_the_output_rises_or_falls_with_the_load_as_the_fsr_sits():
    r = np.array([100.0, 10.0])  # unloading -> loading
    assert np.diff(volts_of(r, CIRCUITS[0]))[0] > 0  # FSR at the supply: rises with force
    assert np.diff(volts_of(r, CIRCUITS[1]))[0] < 0  # FSR at ground: falls
    assert np.diff(volts_of(r, CIRCUITS[2]))[0] > 0  # transimpedance: linear in conductance


@pytest.mark.parametrize("fe", CIRCUITS, ids=lambda fe: f"{fe.circuit}-{getattr(fe, 'fsr_at', '')}")
def test_one_frame_inverts_to_the_same_bits_as_the_array_path(fe):
    # Given readings across the whole range, the rails and beyond them included
    rng = np.random.default_rng(3)
    top = getattr(fe, "supply_v", 1.2)
    volts = np.concatenate([[0.0, 1e-9, top, top + 1.0], rng.uniform(0.0, top, 401)])
    # When each frame of three is inverted as the cue tracker does it, and the whole as an array
    frames = [conductance_us_of_frame(row.tolist(), fe) for row in volts.reshape(-1, 3)]
    # Then the values are the same to the last bit
    assert np.array_equal(np.array(frames).ravel(), conductance_us(volts, fe))


def test_a_reading_at_the_rail_inverts_to_a_finite_resistance():
    fe = CIRCUITS[0]
    g = conductance_us(np.array([0.0, 5.0, 7.0]), fe)
    assert np.isfinite(g).all() and (g > 0).all()


def test_none_is_a_declaration_that_no_circuit_is_known():
    meta = SensorMeta(unit_id="u", channels=["a"], units="volts", front_end={"circuit": "none"})
    assert isinstance(meta.front_end, Undeclared) and not is_declared(meta.front_end)
    assert not is_declared(SensorMeta(unit_id="u", channels=["a"], units="volts").front_end)
    assert is_declared(CIRCUITS[2])


def test_a_declared_front_end_and_a_shared_clock_are_kept_through_ingest(raw_dir, tmp_path):
    # Given lab-bench-a declaring its divider and that both streams share one clock
    replace_in(
        raw_dir / A / "batch.yaml",
        "kept as metadata\n",
        "kept as metadata\n  front_end: {circuit: divider, supply_v: 5.0, fixed_kohm: 4.7, fsr_at: ground}\n",
    )
    replace_in(raw_dir / A / "batch.yaml", "  frame: tissue\n", "  frame: tissue\n  clock: shared\n")
    # When it is ingested
    result = run([raw_dir], tmp_path / "out")
    # Then it is accepted, the circuit and the clock in its batch.json as declared
    assert result.accepted == [A] and result.problems == []
    meta = json.loads((tmp_path / "out" / A / "batch.json").read_text())
    assert meta["sensor"]["front_end"] == {
        "circuit": "divider",
        "supply_v": 5.0,
        "fixed_kohm": 4.7,
        "fsr_at": "ground",
        "series_kohm": 0.0,
    }
    assert meta["reference"]["clock"] == "shared"
