"""Each physical effect of the rig simulator, isolated by switching the others off."""

from __future__ import annotations

import numpy as np
import pytest

from needlecue_runtime.frontend import resistance_of
from pipeline.config import EffectScales
from pipeline.sim import physics

OFF = EffectScales(
    tissue_inhomogeneity=0,
    batch_variation=0,
    gravity=0,
    part_variation=0,
    viscoelasticity=0,
    fsr_threshold=False,
    hysteresis=0,
    drift=0,
    repeatability=0,
    electrical_noise=0,
    adc=False,
    clock_jitter=0,
    dropped_samples=0,
    clock_offset=0,
    reference_noise=0,
    alignment=0,
    unit_drift=0,
)
EST = physics.Estimator()
ONE = np.ones(3)


def only(**on: float | bool) -> EffectScales:
    return OFF.model_copy(update=on)


def volts(load: np.ndarray, effects: EffectScales, t_loaded: np.ndarray | None = None) -> np.ndarray:
    t = np.zeros(len(load)) if t_loaded is None else t_loaded
    return physics.fsr_volts(load, t, EST, effects, ONE, np.random.default_rng(0))


def trial(angle: float = 30.0, effects: EffectScales = OFF, seed: int = 1) -> physics.TrialRecord:
    return physics.simulate_trial(
        angle, physics.Tissue(), EST, effects, physics.Clocks(), np.random.default_rng(seed)
    )


def test_fsr_has_a_threshold_and_saturates():
    # Given a load ramp on one FSR from nothing to far beyond its range
    load = np.repeat(np.linspace(0.0, 40.0, 4001)[:, None], 3, axis=1)
    # When it is read with only the actuation threshold on
    v = volts(load, only(fsr_threshold=True))[:, 0]
    # Then below actuation the divider reads almost nothing, just above it jumps up
    below = load[:, 0] < EST.actuation_n - 5 * EST.actuation_width_n
    assert v[below].max() < 0.01
    just_above = np.searchsorted(load[:, 0], EST.actuation_n + 5 * EST.actuation_width_n)
    assert v[just_above] > 0.2
    # And it rises monotonically towards, but never past, the ceiling set by R_i
    ceiling = EST.front_end.supply_v / (1 + EST.ri_kohm / EST.front_end.fixed_kohm)
    assert np.all(np.diff(v) >= -1e-12)
    assert v[-1] < ceiling
    assert v[-1] > 0.9 * ceiling
    # And the 10-bit ADC clips rather than wraps
    counts = physics.adc_counts(np.array([-1.0, 2.5, 7.0]), 10, 5.0)
    assert counts.tolist() == [0, 512, 1023]


def test_without_threshold_light_loads_read():
    # Given a light load below actuation
    load = np.full((1, 3), 0.05)
    # When read with and without the threshold
    with_threshold = volts(load, only(fsr_threshold=True))[0, 0]
    without = volts(load, OFF)[0, 0]
    # Then only the threshold hides it
    assert with_threshold < 0.005 < without


def test_preload_puts_each_fsr_mid_curve():
    # Given the cast-in preload and nothing else
    v = volts(np.array([EST.preloads_n]), only(fsr_threshold=True))[0]
    # Then each FSR sits well above zero and well below saturation (about 0.6 V of 4.3 V)
    assert np.all((v > 0.4) & (v < 1.0))


def test_tripod_reproduces_the_paper_fea_pattern():
    # Given the paper's FEA load (0.3, 0.6, 1.0) N on the needle, in the estimator frame at 0 deg
    frame = physics.needle_frame(0.0, 60.0)
    on_needle = np.array([[0.3, 0.6, 1.0]])
    # When mapped onto the three FSRs (the force on the tissue is the opposite)
    loads = physics.fsr_loads(-on_needle @ frame.T, frame, EST, OFF) - np.asarray(EST.preloads_n)
    # Then two FSRs are pressed and one unloads, as the FEA's -0.392, -0.229, +0.159 mm show
    assert (loads > 0).sum() == 2 and (loads < 0).sum() == 1
    # And the axial part loads all three equally
    axial = physics.fsr_loads(-np.array([[0, 0, 1.0]]) @ frame.T, frame, EST, OFF)[0]
    assert np.allclose(axial - EST.preloads_n, 1 / 3)


def test_contact_loss_reads_as_an_open_fsr():
    # Given a lateral load strong enough to lift the silicone off one FSR
    load = np.array([[0.49 - 1.0, 1.2, 1.2]])
    # When read
    v = volts(load, OFF)[0]
    # Then the unloaded FSR reads as an open circuit (R over 10 MOhm): a few mV at most
    assert v[0] < 0.01 < v[1]


def test_hysteresis_reads_higher_while_unloading():
    # Given a load cycle up to 2 N and back down
    up = np.linspace(0.49, 2.0, 200)
    load = np.repeat(np.concatenate([up, up[::-1]])[:, None], 3, axis=1)
    # When read with hysteresis on
    v = volts(load, only(hysteresis=1.0))[:, 0]
    # Then at the same load (1.2 N) the unloading branch reads higher, by about the datasheet's 10 %
    i_up = np.argmin(np.abs(up - 1.2))
    i_down = len(load) - 1 - i_up
    r_up, r_down = resistance_of(v[[i_up, i_down]], EST.front_end) - EST.ri_kohm
    assert v[i_down] > v[i_up]
    assert 0.07 < (r_up - r_down) / r_up < 0.13
    # And without hysteresis both branches agree
    v0 = volts(load, OFF)[:, 0]
    assert v0[i_down] == pytest.approx(v0[i_up])


def test_drift_is_logarithmic_in_time_under_load():
    # Given a constant extra load held for 1000 s
    t = np.array([0.0, 1.0, 10.0, 100.0, 1000.0])
    load = np.full((5, 3), 1.5)
    # When read with drift on
    v = volts(load, only(drift=1.0), t_loaded=t)[:, 0]
    # Then the reading creeps up, by similar steps per decade, each under 5 %
    assert np.all(np.diff(v) > 0)
    steps = np.diff(v[1:]) / v[1:-1]
    assert np.all(steps < 0.05)
    assert steps.max() / steps.min() < 1.5
    # And without drift it holds still
    assert np.ptp(volts(load, OFF, t_loaded=t)) == 0


def test_silicone_creep_delays_part_of_a_step():
    # Given a 1 N load step at t = 1 s on a 200 Hz grid
    dt = 0.005
    t = np.arange(0, 10, dt)
    load = np.where(t[:, None] >= 1.0, 1.5, 0.5) * ONE
    # When passed through the silicone
    out = physics.creep(load, dt, EST, 1.0)[:, 0]
    # Then only part of the step arrives at once, the rest within a few time constants
    just_after = out[np.searchsorted(t, 1.0 + dt)]
    assert just_after == pytest.approx(0.5 + (1 - EST.creep_fraction), abs=0.01)
    assert out[-1] == pytest.approx(1.5, abs=0.01)
    # And without viscoelasticity the step passes untouched
    assert np.array_equal(physics.creep(load, dt, EST, 0.0), load)


def test_force_profile_has_puncture_friction_and_pull():
    # Given the default tissue and robot programme
    m, tissue = physics.Motion(), physics.Tissue()
    t = np.arange(0, m.duration_s, 0.001)
    f = physics.needle_force_profile(t, m, tissue)
    total = f.tip + f.friction
    # Then the force builds like a spring and drops sharply at puncture
    drop = np.diff(total).min()
    assert drop < -0.25 * total.max()
    # And grows with friction while inserting past puncture
    ins = (f.phase == 1) & ~f.spring & (t > t[np.argmin(np.diff(total))] + 0.5)
    assert np.all(np.diff(total[ins]) > 0)
    # And the tissue pulls on the needle (negative) while retracting, then rests at zero
    assert total[f.phase == 3].min() < -0.1
    assert abs(total[-1]) < 1e-3
    assert np.all(total[t < m.rest_before_s] == 0)


def test_retraction_pull_reads_below_the_preload_point():
    # Given a simulated trial with the whole sensing chain
    rec = trial(0.0, only(fsr_threshold=True, viscoelasticity=1.0, hysteresis=1.0))
    phase = rec.truth["phase"]
    total = rec.truth["volts"].sum(axis=1)
    rest = total[(phase == 0) & (rec.truth["t_sample"] < 1.0)].mean()
    # When the lifted tissue pulls back at the end of retraction (upward force on the tissue)
    pulling = np.flatnonzero((phase == 3) & (rec.truth["force"][:, 2] > 0.05))
    late = pulling[-len(pulling) // 3 :]  # the silicone's lag has played out by then
    # Then the estimator reads below where it started
    assert len(late) > 10
    assert np.all(total[late] < rest)


def test_tilt_rotates_the_reaction_and_gravity_presses_differently():
    # Given identical tissue at two insertion angles
    at0, at45 = trial(0.0), trial(45.0)
    # Then at full depth the reaction points along each needle, 45 deg apart in the tissue frame
    f0, f45 = (r.truth["force"][r.truth["phase"] == 2].mean(axis=0) for r in (at0, at45))
    cos = f0 @ f45 / np.linalg.norm(f0) / np.linalg.norm(f45)
    assert np.degrees(np.arccos(cos)) == pytest.approx(45, abs=10)
    # And with gravity on, the FSRs at rest carry a different load at each angle
    rest = []
    for angle in (0.0, 75.0):
        frame = physics.needle_frame(angle, 60.0)
        rest.append(physics.fsr_loads(np.zeros((1, 3)), frame, EST, only(gravity=1.0))[0])
    assert np.abs(rest[0] - rest[1]).max() > 0.01
    assert np.allclose(physics.fsr_loads(np.zeros((1, 3)), frame, EST, OFF)[0], EST.preloads_n)


def test_reference_stream_is_offset_from_the_estimator_clock():
    # Given a trial with a clock offset and no noise
    rec = trial(30.0, only(clock_offset=1.0), seed=3)
    assert abs(rec.clock_offset_s) > 0.02
    # When the reference is read on its own clock versus shifted by the offset
    onset_ref = rec.t_s[np.argmax(np.linalg.norm(rec.force, axis=1) > 0.01)]
    onset_true = rec.truth["t_sample"][np.argmax(np.linalg.norm(rec.truth["force"], axis=1) > 0.01)]
    # Then only the shifted reference agrees with the estimator's time line (within a sample)
    assert abs(onset_ref + rec.clock_offset_s - onset_true) <= 1 / 30
    assert abs(onset_ref - onset_true) > abs(rec.clock_offset_s) - 1 / 30


def test_host_clock_jitters_and_drops_samples():
    # Given the estimator stream with jitter and many dropped samples
    rec = trial(30.0, only(clock_jitter=1.0, dropped_samples=10.0), seed=4)
    dt = np.diff(rec.t_ms)
    # Then stamps are strictly increasing, irregular by milliseconds, and some samples are missing
    assert np.all(dt > 0)
    regular = dt[dt < 1.5 * 1000 / 30]
    assert 0.5 < regular.std() < 5.0
    assert (dt > 1.5 * 1000 / 30).sum() >= 5
    # And without those effects the stream is perfectly regular
    clean = np.diff(trial(30.0, OFF).t_ms)
    assert np.allclose(clean, 1000 / 30, atol=1e-3)


def test_reference_has_the_nano17_resolution():
    rec = trial(30.0, only(reference_noise=1.0))
    steps = rec.force / physics.Clocks().ref_resolution_n
    assert np.allclose(steps, np.round(steps), atol=1e-6)


AS_PUBLISHED = EffectScales()
UNITS_ALIKE = EffectScales(part_variation=0, alignment=0, unit_drift=0)  # every per-unit switch off


def unit(seed: int, effects: EffectScales = AS_PUBLISHED) -> physics.Estimator:
    return physics.draw_estimator(np.random.default_rng(seed), effects)


def test_units_differ_and_each_is_drawn_the_same_every_time():
    # Given two unit seeds, each drawn twice with every effect as published
    a, b = unit(1), unit(2)
    # Then a unit is the same every time it is drawn
    assert unit(1) == a
    # And two units differ in gains, preloads, FSR placement and drift
    assert a.gains != b.gains and a.preloads_n != b.preloads_n
    assert a.azimuths_deg != b.azimuths_deg and a.drift_per_decade != b.drift_per_decade
    # And each unit's drift stays under the datasheet's 5 % per decade
    assert all(0.025 <= unit(seed).drift_per_decade < 0.05 for seed in range(20))


def test_with_every_unit_switch_off_all_units_are_the_nominal_one():
    # Given part variation, alignment and unit drift all off, then any two units are the nominal unit
    assert unit(1, UNITS_ALIKE) == unit(2, UNITS_ALIKE) == physics.Estimator()


def test_the_per_fsr_draws_come_first_and_the_per_unit_ones_are_appended():
    # Given the three per-FSR draws done by hand, in their order (placement, gain, preload)
    rng = np.random.default_rng(7)
    azimuths = np.array([90.0, 210.0, 330.0]) + rng.normal(0, 3.0, 3)
    gains = 1.0 + rng.normal(0, 0.06, 3)
    preloads = 0.49 * (1.0 + rng.normal(0, 0.10, 3))
    # When the unit is drawn from the same seed with the alignment and unit drift switched off
    est = unit(7, EffectScales(alignment=0, unit_drift=0))
    # Then those draws are the unit's, and the drift is the nominal one
    assert np.allclose(est.azimuths_deg, azimuths) and np.allclose(est.gains, gains)
    assert (
        np.allclose(est.preloads_n, preloads) and est.drift_per_decade == physics.Estimator().drift_per_decade
    )


def test_alignment_rotates_the_whole_tripod_and_changes_nothing_else():
    # Given one unit drawn with and without the connector alignment
    turned, straight = unit(3), unit(3, EffectScales(alignment=0))
    # Then all three FSRs turn by the same angle, and the other draws are untouched
    turn = np.subtract(turned.azimuths_deg, straight.azimuths_deg)
    assert np.allclose(turn, turn[0]) and abs(turn[0]) > 0.01
    assert (turned.gains, turned.preloads_n) == (straight.gains, straight.preloads_n)
    assert turned.drift_per_decade == straight.drift_per_decade
    # And a larger scale turns it further, by the same draw
    assert np.allclose(
        np.subtract(unit(3, EffectScales(alignment=2)).azimuths_deg, straight.azimuths_deg), 2 * turn
    )


def test_unit_drift_off_gives_the_nominal_drift_and_keeps_the_other_draws():
    own, nominal = unit(4), unit(4, EffectScales(unit_drift=0))
    assert nominal.drift_per_decade == physics.Estimator().drift_per_decade != own.drift_per_decade
    assert (own.azimuths_deg, own.gains, own.preloads_n) == (
        nominal.azimuths_deg,
        nominal.gains,
        nominal.preloads_n,
    )
