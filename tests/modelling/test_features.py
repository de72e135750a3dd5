"""The model's inputs from volts: the divider inverted, the rest reading, batch and stream alike."""

from __future__ import annotations

import numpy as np
import pytest

from needlecue_runtime.features import (
    InputTransform,
    ModelInputs,
    RestReading,
    features,
    features_at,
    spec_of,
)
from needlecue_runtime.frontend import Divider, conductance_us, volts_of
from pipeline.config import EffectScales
from pipeline.sim import physics, rigs

QUIET = EffectScales(
    fsr_threshold=False,
    hysteresis=0,
    drift=0,
    repeatability=0,
    electrical_noise=0,
    adc=False,
    viscoelasticity=0,
)


def _volts(load: np.ndarray, est: physics.Estimator) -> np.ndarray:
    gain = np.ones(est.n_fsr)
    return physics.fsr_volts(load, np.zeros(len(load)), est, QUIET, gain, np.random.default_rng(0))


CIRCUIT = rigs.declared_front_end(physics.Estimator())  # what the simulator's batches declare


def _spec(kind: str) -> ModelInputs:
    return ModelInputs(kind=kind, front_end=CIRCUIT if kind.endswith("conductance") else None)


def test_conductance_inverts_the_simulated_divider() -> None:
    # given: loads on an ideal unit (no threshold, noise or hysteresis), read through the divider
    est = physics.Estimator()
    load = np.linspace(0.2, 3.0, 30)[:, None].repeat(3, axis=1)
    # when: inverting the divider the batches declare
    g = features(_volts(load, est), np.zeros(30, np.int64), np.arange(30) / 30, _spec("conductance"))
    # then: conductance is load / (2 R_S), as the FSR law says, in µS (plus the open FSR's 0.1 µS)
    np.testing.assert_allclose(g, load / (2 * est.rs_kohm_n) * 1e3 + 1e3 / est.r_open_kohm, rtol=1e-6)


def test_conductance_needs_a_declared_circuit_and_says_so() -> None:
    with pytest.raises(ValueError, match=r"none is declared \(batch\.yaml sensor\.front_end"):
        ModelInputs(kind="rest_conductance")
    assert ModelInputs(kind="rest_volts").front_end is None


def test_a_model_from_before_circuits_were_data_keeps_its_divider() -> None:
    stored = {
        "kind": "rest_conductance",
        "v_plus": 5.0,
        "r_m_kohm": 10.0,
        "r_series_kohm": 1.62,
        "r_open_kohm": 10000.0,
        "rest_s": 0.5,
    }
    spec = spec_of(stored)
    assert spec.front_end == CIRCUIT and spec.kind == "rest_conductance"
    assert spec_of({"kind": "volts", "v_plus": 5.0, "rest_s": 0.5}).front_end is None


def test_a_unit_with_its_own_circuit_is_read_through_it() -> None:
    # given: the same FSR conductances read by the default divider and by a 3.3 V ground-side one
    other = rigs.declared_front_end(rigs.rig("divider-3v3-ground"))
    r = np.geomspace(5.0, 500.0, 40)[:, None].repeat(3, axis=1)
    codes, t = np.zeros(40, np.int64), np.arange(40) / 30
    spec = _spec("conductance")
    # when: each reading goes through its own circuit
    mine = features(volts_of(r, CIRCUIT), codes, t, spec)
    theirs = features(volts_of(r, other), codes, t, spec.through(other))
    # then: the same inputs, though the volts fall where the others rise
    np.testing.assert_allclose(mine, theirs, rtol=1e-9)
    assert spec.through(None) is spec and _spec("volts").through(other).front_end is None


def test_rest_conductance_removes_the_preload() -> None:
    # given: two units that differ only in their cast-in preloads, under the same added load
    a = physics.Estimator(preloads_n=(0.45, 0.49, 0.55))
    b = physics.Estimator(preloads_n=(0.52, 0.40, 0.50))
    extra = np.concatenate([np.zeros(20), np.linspace(0, 0.5, 40)])[:, None].repeat(3, axis=1)
    t = np.arange(len(extra)) / 30.0
    codes = np.zeros(len(extra), np.int64)
    spec = _spec("rest_conductance")
    # when: computing their inputs
    fa = features(_volts(np.asarray(a.preloads_n) + extra, a), codes, t, spec)
    fb = features(_volts(np.asarray(b.preloads_n) + extra, b), codes, t, spec)
    # then: the same inputs, while the raw volts differ
    np.testing.assert_allclose(fa, fb, atol=1e-9)
    va, vb = _volts(np.asarray(a.preloads_n) + extra, a), _volts(np.asarray(b.preloads_n) + extra, b)
    assert not np.allclose(va, vb)


@pytest.mark.parametrize("kind", ["volts", "rest_volts", "conductance", "rest_conductance"])
def test_streaming_gives_the_batch_numbers_and_is_causal(kind: str) -> None:
    # given: two interleaved trials of noisy volts
    rng = np.random.default_rng(1)
    volts = 0.6 + 0.3 * rng.random((80, 3))
    codes = np.repeat([0, 1], 40)
    t = np.tile(np.arange(40) / 30.0, 2)
    spec = _spec(kind)
    order = rng.permutation(80)
    # when: computing them in a shuffled batch and one sample at a time
    batch = np.empty((80, 3))
    batch[order] = features(volts[order], codes[order], t[order], spec)
    stream = RestReading(spec.rest_s, 3)
    streamed = []
    for i in range(80):
        if i in (0, 40):
            stream.reset()
        streamed.append(features_at(volts[i], stream.push(float(t[i]), volts[i]), spec))
    changed = volts.copy()
    changed[30:40] += 0.5
    later = features(changed, codes, t, spec)
    # then: equal, and changing later samples leaves earlier inputs alone
    np.testing.assert_allclose(np.asarray(streamed), batch, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(later[:30], batch[:30])


def test_a_transform_round_trips_and_rejects_a_bad_matrix() -> None:
    t = InputTransform.from_dict({"matrix": [[1.1, 0.0], [0.2, 0.9]], "offset": [0.0, 0.1]})
    assert InputTransform.from_dict(t.to_dict()) == t
    np.testing.assert_allclose(t.on_inputs(np.array([[1.0, 2.0]])), [[1.1, 0.2 + 1.8 + 0.1]])
    np.testing.assert_array_equal(t.on_volts(np.array([[1.0, 2.0]])), [[1.0, 2.0]])  # not its domain
    with pytest.raises(ValueError, match="finite square matrix"):
        InputTransform.from_dict({"matrix": [[1.0, 0.0]], "offset": [0.0]})
    with pytest.raises(ValueError, match="needs the unit's circuit"):
        InputTransform.from_dict({"matrix": [[1.0]], "offset": [0.0], "domain": "conductance"})


def test_a_conductance_map_scales_each_fsr_s_conductance_before_the_inputs() -> None:
    # given: a 5 V, 10 kOhm divider unit whose first FSR reads 10 % more conductance than the average
    fe = Divider(circuit="divider", supply_v=5.0, fixed_kohm=10.0)
    t = InputTransform.from_dict(
        {"matrix": [[1 / 1.1, 0.0], [0.0, 1.0]], "offset": [0.0, 0.0], "domain": "conductance"}, fe
    )
    g = np.array([[110.0, 50.0], [220.0, 80.0]])  # µS
    volts = volts_of(1e3 / g, fe)
    # when: mapped
    mapped = t.on_volts(volts)
    # then: the volts of the calibrated conductance, through the unit's circuit; the inputs untouched
    np.testing.assert_allclose(conductance_us(mapped, fe), [[100.0, 50.0], [200.0, 80.0]], rtol=1e-9)
    np.testing.assert_array_equal(t.on_inputs(mapped), mapped)
    assert InputTransform.from_dict(t.to_dict(), fe) == t
