"""Physics of the needle-insertion rig, for the built-in simulator.

Pure numpy, no I/O. One trial is simulated in four steps, each a function here:

1. `needle_force_profile`: the needle-tissue force along the needle over time
   (Okamura, Simone & O'Leary 2004: nonlinear spring before puncture, rupture drop,
   cutting + Karnopp friction while inserting, relaxation at the dwell, reversed
   friction and a lifted tissue pulling back while retracting).
2. `force_on_tissue`: that force as a 3-D vector in the reference sensor's (tissue)
   frame, for a needle tilted at the insertion angle, with the bevel's lateral force.
3. `fsr_loads`: the same reaction rotated into the tilted estimator's frame plus the
   needle's own weight, mapped by the tripod onto each FSR on top of the cast-in preload.
4. `fsr_volts`: silicone creep, contact loss, FSR threshold / conductance law /
   hysteresis / drift, the voltage divider; then `adc_counts`.

Every figure comes from `docs/physics.md` (paper sections II-IV, the Interlink FSR 400
datasheet, a published FSR-under-silicone calibration, the paper's FEA) unless a
comment says it is an assumption of ours. Effects are scaled by `EffectScales`
(1 = as published, 0 = off) so tests can isolate each one.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import NamedTuple

import numpy as np
from scipy.signal import lfilter

from needlecue_runtime.frontend import Circuit, Divider, Transimpedance, volts_of
from pipeline.config import EffectScales

G = 9.81  # m/s^2


# --------------------------------------------------------------------------- tissue
@dataclass(frozen=True)
class Motion:
    """The UR5's programme (paper section IV): 1 mm/s for 10 s in, 2 mm/s out."""

    rest_before_s: float = 2.0
    insertion_speed_mm_s: float = 1.0
    insertion_time_s: float = 10.0
    dwell_s: float = 0.8  # assumption: the robot pauses briefly before reversing
    retraction_speed_mm_s: float = 2.0
    rest_after_s: float = 2.5

    @property
    def travel_mm(self) -> float:
        return self.insertion_speed_mm_s * self.insertion_time_s

    @property
    def t_dwell(self) -> float:
        return self.rest_before_s + self.insertion_time_s

    @property
    def t_retract(self) -> float:
        return self.t_dwell + self.dwell_s

    @property
    def t_out(self) -> float:
        return self.t_retract + self.travel_mm / self.retraction_speed_mm_s

    @property
    def duration_s(self) -> float:
        return self.t_out + self.rest_after_s


@dataclass(frozen=True)
class Tissue:
    """Needle-tissue constants at one tissue point (Okamura et al. 2004 model).

    Magnitudes are chosen so that the force at maximum depth is of the order the paper
    reports (|F| about 0.6 N, paper section IV); they are not fitted to any model's
    accuracy.
    """

    gap_mm: float = 1.0  # needle tip starts this far above the surface
    a1_n_mm: float = 0.05  # stiffness: f = a1*x + a2*x^2 before puncture
    a2_n_mm2: float = 0.02
    puncture_mm: float = 4.0  # depth at which the capsule ruptures
    cutting_n: float = 0.20  # constant cutting force for a tissue
    friction_in_n_mm: float = 0.035  # Karnopp Coulomb term per inserted mm, inserting
    friction_out_n_mm: float = 0.030  # ... retracting (different coefficient)
    viscous_n_s_mm2: float = 0.004  # Karnopp viscous term per inserted mm per mm/s
    grip_n: float = 0.10  # assumption: the surface layer grips the shaft until the tip exits
    tent_n_mm: float = 0.12  # assumption: stiffness of the tissue lifted by the shaft
    relax_fraction: float = 0.3  # tissue relaxation at the dwell (viscoelastic tissue)
    relax_tau_s: float = 0.7
    bevel_ratio: float = 0.3  # assumption: bevel-tip lateral force / tip force
    bevel_deg: float = 30.0  # bevel orientation in the estimator frame


class ForceProfile(NamedTuple):
    """Needle-tissue force along the insertion direction (N; + = pushing into the tissue)."""

    tip: np.ndarray  # spring before puncture, cutting after; drives the bevel's lateral force
    friction: np.ndarray  # along the shaft; negative = pulling the tissue up while retracting
    spring: np.ndarray  # True while the intact surface is indented (before puncture)
    phase: np.ndarray  # index into vocab.PHASES


def needle_force_profile(t: np.ndarray, motion: Motion, tissue: Tissue) -> ForceProfile:
    """The Okamura et al. (2004) force model over times `t` (s) of one trial."""
    m = motion
    max_depth = max(m.travel_mm - tissue.gap_mm, 0.0)
    rupture = tissue.puncture_mm if max_depth > tissue.puncture_mm else np.inf
    travel = np.clip(t - m.rest_before_s, 0.0, m.insertion_time_s) * m.insertion_speed_mm_s
    back = np.clip(t - m.t_retract, 0.0, None) * m.retraction_speed_mm_s
    depth = np.clip(travel - back - tissue.gap_mm, 0.0, None)  # tip below the surface
    in_depth = np.clip(travel - tissue.gap_mm, 0.0, None)  # deepest point reached so far

    inserting = (t >= m.rest_before_s) & (t < m.t_dwell)
    dwelling = (t >= m.t_dwell) & (t < m.t_retract)
    retracting = (t >= m.t_retract) & (t < m.t_out)
    pushing = inserting | dwelling

    # Inserting: a nonlinear spring up to the rupture depth, then the force drops to the
    # cutting force plus Karnopp friction (Coulomb + viscous) along the inserted shaft.
    punctured = in_depth >= rupture
    spring_force = tissue.a1_n_mm * in_depth + tissue.a2_n_mm2 * in_depth**2
    tip = np.where(punctured, tissue.cutting_n, spring_force) * (in_depth > 0)
    v_in = m.insertion_speed_mm_s
    fric = np.where(punctured, (tissue.friction_in_n_mm + tissue.viscous_n_s_mm2 * v_in) * in_depth, 0.0)
    # Dwell: inside the Karnopp dead band the shaft sticks and the tissue relaxes. The factor
    # is frozen at the end of the dwell, so at retraction times tip/fric hold those values.
    held = np.clip(np.minimum(t, m.t_retract) - m.t_dwell, 0.0, None)
    relax = 1.0 - tissue.relax_fraction * (1.0 - np.exp(-held / tissue.relax_tau_s))
    tip, fric = tip * relax, fric * relax

    # Retracting: the tip unloads within a fraction of a millimetre, friction reverses and
    # lifts the tissue like a tent until the tent's pull reaches the sliding friction; the
    # surface layer keeps its grip until the tip is out.
    v_out = m.retraction_speed_mm_s
    unload = np.exp(-back / 0.25)
    capacity = (tissue.friction_out_n_mm + tissue.viscous_n_s_mm2 * v_out) * depth + tissue.grip_n
    pull = np.minimum(tissue.tent_n_mm * back, capacity)
    inside = depth > 0
    ret_fric = np.where(inside, fric * unload - pull * (1.0 - unload), 0.0)
    # Once the tip is out, the lifted tissue springs back within a fraction of a second.
    t_exit = m.t_retract + max_depth / v_out
    last_pull = min(tissue.tent_n_mm * max_depth, tissue.grip_n)
    rebound = -last_pull * np.exp(-np.clip(t - t_exit, 0.0, None) / 0.12)
    after = (t >= t_exit) & ~inside & (t >= m.t_retract)
    fric = np.where(pushing, fric, np.where(retracting & inside, ret_fric, np.where(after, rebound, 0.0)))
    tip = np.where(pushing, tip, np.where(retracting, tip * unload * inside, 0.0))

    phase = np.zeros(t.shape, dtype=np.int8)
    phase[inserting], phase[dwelling], phase[retracting] = 1, 2, 3
    return ForceProfile(tip, fric, pushing & ~punctured & (in_depth > 0), phase)


# --------------------------------------------------------------------------- geometry
def needle_frame(angle_deg: float, azimuth_deg: float) -> np.ndarray:
    """Rotation from the estimator's frame to the tissue frame.

    The estimator's z axis runs along the needle back towards the robot; at 0 deg the
    needle points straight down. The robot tilts it by the insertion angle about a
    horizontal axis; `azimuth_deg` is where the robot stands relative to the reference
    sensor's x axis (an assumption: the paper does not give it; 60 deg puts force on all
    three reference axes as in its Fig. 6).
    """
    th, ph = np.radians(angle_deg), np.radians(azimuth_deg)
    axis = np.array([-np.sin(ph), np.cos(ph), 0.0])
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(th) * k + (1 - np.cos(th)) * (k @ k)  # Rodrigues


def force_on_tissue(profile: ForceProfile, frame: np.ndarray, tissue: Tissue) -> np.ndarray:
    """3-D force of the needle on the tissue, in the tissue (reference sensor) frame, (n, 3).

    Cutting and friction act along the needle. Before puncture the indented surface
    pushes back between the needle axis and the surface normal (we take the bisector),
    so at steep angles the spring phase has a component across the needle. The bevel
    tip adds a lateral force proportional to the tip force.
    """
    d = frame @ np.array([0.0, 0.0, -1.0])  # insertion direction, into the tissue
    normal = np.array([0.0, 0.0, -1.0])
    bisector = (d + normal) / np.linalg.norm(d + normal)
    b = np.radians(tissue.bevel_deg)
    bevel = frame @ np.array([np.cos(b), np.sin(b), 0.0])
    tip = profile.tip[:, None]
    tip_dir = np.where(profile.spring[:, None], bisector, d)
    return tip * tip_dir + profile.friction[:, None] * d + tissue.bevel_ratio * tip * bevel


# --------------------------------------------------------------------------- estimator
NOMINAL_FRONT_END = Divider(circuit="divider", supply_v=5.0, fixed_kohm=10.0)  # frozen: a safe default


@dataclass(frozen=True)
class Estimator:
    """One physical estimator unit: tripod, FSRs, silicone and read-out circuit."""

    n_fsr: int = 3
    azimuths_deg: tuple[float, ...] = (90.0, 210.0, 330.0)  # three FSRs at 120 deg
    gains: tuple[float, ...] = (1.0, 1.0, 1.0)  # part-to-part, +/-6 % (datasheet)
    preloads_n: tuple[float, ...] = (0.49, 0.49, 0.49)  # 50 g cast in: each FSR mid-curve
    # Lateral lever of the tripod: fitted to the paper's FEA, where (0.3, 0.6, 1.0) N moves
    # the silicone over the FSRs by -0.392, -0.229, +0.159 mm (one FSR unloads).
    lateral_lever: float = 1.05
    moving_mass_g: float = 5.0  # assumption: needle, hub and connector on the FSRs
    creep_fraction: float = 0.3  # standard linear solid: part of the load arrives with a lag
    creep_tau_s: float = 1.5  # "time constants of the order of seconds"
    actuation_n: float = 0.15  # paper: 10 g gives no change, 20 g a sudden spike
    actuation_width_n: float = 0.01
    rs_kohm_n: float = 17.0  # R = 2*R_S/F + R_i (published calibration under silicone)
    law_exponent: float = 1.0  # G ∝ F^n: 1 = the published calibration; other FSRs follow n < 1
    ri_kohm: float = 1.62  # series term with a thin silicone layer
    r_open_kohm: float = 10_000.0  # unloaded FSR: over 10 MOhm (datasheet)
    hysteresis: float = 0.10  # (R_F+ - R_F-)/R_F+ about +10 % (datasheet)
    hysteresis_scale_n: float = 0.05  # assumption: load change over which the loop closes
    drift_per_decade: float = 0.04  # "under 5 % per decade of time under constant load"
    # read-out: V_out = V+ / (1 + R_FSR / R_M), R_M = 10 kOhm, V+ = 5 V (needlecue_runtime.frontend)
    front_end: Circuit = NOMINAL_FRONT_END
    rail_v: float = 5.0  # an op-amp's output cannot leave 0..rail
    noise_v: float = 0.0015  # assumption: electrical noise, about a third of an ADC count
    adc_bits: int = 10  # Arduino Uno
    vref_v: float = 5.0
    # how units of this design differ (draw_estimator): part-to-part gain, one standard deviation
    gain_sd: float = 0.06

    @property
    def directions(self) -> np.ndarray:
        a = np.radians(np.asarray(self.azimuths_deg))
        return np.stack([np.cos(a), np.sin(a)], axis=1)


def draw_estimator(
    rng: np.random.Generator, effects: EffectScales, base: Estimator = Estimator()
) -> Estimator:
    """One estimator unit of design `base` (a rig of `pipeline.sim.rigs`): how it differs from the
    nominal unit (`docs/physics.md`, section 4).

    Per FSR (`part_variation`): placement (azimuth, N(0, 3 deg), assumption), transfer gain (1 +
    N(0, `gain_sd`), FSR datasheet: +/-6 % part to part) and cast-in preload (nominal x (1 + N(0,
    10 %)), assumption). Per unit: the connector's alignment rotates the whole tripod (N(0, 5 deg)
    added to all three azimuths, `alignment`, assumption), and the unit's own drift per decade,
    U(0.025, 0.05) (datasheet: under 5 % per decade; used when `unit_drift` > 0, else the design's
    nominal). The draws come in that order, all of them whatever the switches, so a switch never
    changes the other draws. With the three switches at 0 every unit is the nominal one.
    """
    s = effects.part_variation
    azimuths = np.asarray(base.azimuths_deg) + s * rng.normal(0, 3.0, 3)
    gains = 1.0 + s * rng.normal(0, base.gain_sd, 3)
    preloads = np.asarray(base.preloads_n) * (1.0 + s * rng.normal(0, 0.10, 3))
    # Appended after the three draws above, so that they stay what they were.
    rotation = effects.alignment * rng.normal(0, 5.0)  # assumption: connector keyed within a few deg
    drift = float(rng.uniform(0.025, 0.05))
    return replace(
        base,
        azimuths_deg=tuple(float(a) for a in azimuths + rotation),
        gains=tuple(float(g) for g in gains),
        preloads_n=tuple(float(f) for f in preloads),
        drift_per_decade=drift if effects.unit_drift > 0 else base.drift_per_decade,
    )


def fsr_loads(
    force_tissue: np.ndarray, frame: np.ndarray, est: Estimator, effects: EffectScales
) -> np.ndarray:
    """Normal load on each FSR (N), (n, n_fsr), before the silicone's dynamics.

    The needle feels the opposite of what it does to the tissue; the estimator sees it
    in its own tilted frame, plus the weight of what hangs on it. The axial component
    loads all FSRs equally, the lateral one differentially through the tripod.
    """
    weight = np.array([0.0, 0.0, -est.moving_mass_g * 1e-3 * G]) * effects.gravity
    f_est = (-force_tissue + weight) @ frame  # rows: frame.T @ f
    axial = f_est[:, 2]  # pushing the needle back compresses the FSRs
    lateral = f_est[:, :2] @ est.directions.T
    share = axial[:, None] / 3 + est.lateral_lever * lateral
    return np.asarray(est.preloads_n) + np.asarray(est.gains) * share


def creep(load: np.ndarray, dt: float, est: Estimator, scale: float) -> np.ndarray:
    """Silicone as a standard linear solid: a fraction of each load change arrives with a lag."""
    beta = min(est.creep_fraction * scale, 1.0)
    if beta == 0:
        return load
    a = np.exp(-dt / est.creep_tau_s)
    lagged = lfilter([1 - a], [1, -a], load - load[0], axis=0) + load[0]  # starts at rest
    return (1 - beta) * load + beta * lagged


def fsr_volts(
    load: np.ndarray,
    t_loaded: np.ndarray,
    est: Estimator,
    effects: EffectScales,
    gain: np.ndarray,
    rng: np.random.Generator,
) -> np.ndarray:
    """Front-end output (V) of each FSR for its load (N) at the sample times, (n, n_fsr).

    `t_loaded` is the time (s) since the trial's extra load began (drift is logarithmic
    in it); `gain` is this trial's repeatability factor per FSR.
    """
    # Contact loss is not optional: when the tripod unloads an FSR past its preload the
    # silicone lifts off it, and an FSR cannot sense tension (clipped at zero below).
    extra = load - np.asarray(est.preloads_n)
    drift = 1.0 + effects.drift * est.drift_per_decade * np.log10(1.0 + np.clip(t_loaded, 0, None))
    load = np.clip(np.asarray(est.preloads_n) + extra * drift[:, None], 0.0, None)

    # 1/kOhm, grows in proportion to force (law_exponent 1), or as a power of it (n < 1: another FSR)
    if est.law_exponent == 1.0:
        conductance = load / (2 * est.rs_kohm_n)
    else:
        conductance = load**est.law_exponent / (2 * est.rs_kohm_n)
    if effects.fsr_threshold:
        conductance = conductance / (1.0 + np.exp(-(load - est.actuation_n) / est.actuation_width_n))
    conductance = conductance * _hysteresis(load, est, effects.hysteresis) * gain
    r = 1.0 / (conductance + 1.0 / est.r_open_kohm) + est.ri_kohm
    v = volts_of(r, est.front_end)
    if isinstance(est.front_end, Transimpedance):  # an op-amp saturates at its rails
        v = np.clip(v, 0.0, est.rail_v)
    return v + effects.electrical_noise * rng.normal(0.0, est.noise_v, v.shape)


def _hysteresis(load: np.ndarray, est: Estimator, scale: float) -> np.ndarray:
    """Conductance factor: lower while loading, higher while unloading (R_F+ > R_F-)."""
    if scale == 0:
        return np.ones_like(load)
    h = est.hysteresis * scale
    z = np.empty_like(load)
    state = np.ones(load.shape[1])  # the cast-in preload was applied by loading
    prev = load[0]
    for i, row in enumerate(load):
        step = row - prev
        target = np.sign(step)
        moved = target != 0
        state[moved] = target[moved] + (state[moved] - target[moved]) * np.exp(
            -np.abs(step[moved]) / est.hysteresis_scale_n
        )
        z[i] = state
        prev = row
    return 1.0 - 0.5 * h * z


def adc_counts(volts: np.ndarray, bits: int, vref: float) -> np.ndarray:
    """10-bit ADC over 0..vref (about 4.9 mV a count), clipped to its range."""
    top = 2**bits - 1
    return np.clip(np.round(volts / vref * top), 0, top).astype(np.int64)


# --------------------------------------------------------------------------- clocks
@dataclass(frozen=True)
class Clocks:
    """Host-stamped estimator stream and the DAQ's own clock (`docs/rig-log-format.md`)."""

    fsr_rate_hz: float = 30.0
    ref_rate_hz: float = 100.0
    latency_ms: float = 4.0  # assumption: USB serial latency, constant part
    jitter_ms: float = 2.0  # "host-side timestamps jitter by milliseconds"
    drop_probability: float = 0.005  # "a sample is occasionally lost"
    max_offset_s: float = 0.3  # "an offset of up to a few hundred milliseconds"
    ref_resolution_n: float = 1 / 320  # Nano17 SI-12-0.12 resolution, about 3 mN
    ref_noise_n: float = 0.002


@dataclass
class TrialRecord:
    """What the rig logged for one trial, plus the ground truth behind it."""

    t_ms: np.ndarray  # estimator stream, host clock
    counts: np.ndarray  # (n, n_fsr)
    t_s: np.ndarray  # reference stream, DAQ clock
    force: np.ndarray  # (m, 3), N, quantised and noisy
    clock_offset_s: float  # reference stamp t_s happened at host time t_s + offset
    truth: dict[str, np.ndarray] = field(default_factory=dict)


def simulate_trial(
    angle_deg: float,
    tissue: Tissue,
    est: Estimator,
    effects: EffectScales,
    clocks: Clocks,
    rng: np.random.Generator,
    motion: Motion = Motion(),
    azimuth_deg: float = 60.0,
) -> TrialRecord:
    """Simulate one insertion trial end to end, as the two streams would log it."""
    dt = 0.005  # 200 Hz internal grid for the silicone dynamics
    t = np.arange(0.0, motion.duration_s + 1.0, dt)
    frame = needle_frame(angle_deg, azimuth_deg)
    profile = needle_force_profile(t, motion, tissue)
    f_tissue = force_on_tissue(profile, frame, tissue)
    load = creep(fsr_loads(f_tissue, frame, est, effects), dt, est, effects.viscoelasticity)

    # Estimator stream: the Arduino samples on its own regular clock, the host stamps the
    # samples on arrival (latency + jitter), and now and then one is lost.
    period = 1.0 / clocks.fsr_rate_hz
    t_sample = np.arange(0.0, motion.duration_s, period)
    keep = rng.random(t_sample.size) >= clocks.drop_probability * effects.dropped_samples
    keep[[0, -1]] = True
    t_sample = t_sample[keep]
    jitter = np.abs(rng.normal(0.0, clocks.jitter_ms, t_sample.size)) * effects.clock_jitter
    t_host = t_sample + (clocks.latency_ms * (effects.clock_jitter > 0) + jitter) * 1e-3
    t_host = np.maximum.accumulate(t_host)  # the host stamps in order of arrival
    sample_load = np.stack([np.interp(t_sample, t, load[:, k]) for k in range(est.n_fsr)], axis=1)
    gain = 1.0 + effects.repeatability * rng.normal(0.0, 0.02, est.n_fsr)  # +/-2 % per part
    volts = fsr_volts(sample_load, t_sample - motion.rest_before_s, est, effects, gain, rng)
    counts = adc_counts(volts, est.adc_bits, est.vref_v) if effects.adc else volts

    # Reference stream: uniform on the DAQ clock, which started `offset` after the host's.
    offset = effects.clock_offset * rng.uniform(-clocks.max_offset_s, clocks.max_offset_s)
    t_ref = np.arange(0.0, motion.duration_s, 1.0 / clocks.ref_rate_hz)
    f_ref = np.stack([np.interp(t_ref + offset, t, f_tissue[:, k]) for k in range(3)], axis=1)
    if effects.reference_noise > 0:
        f_ref = f_ref + rng.normal(0.0, clocks.ref_noise_n * effects.reference_noise, f_ref.shape)
        f_ref = np.round(f_ref / clocks.ref_resolution_n) * clocks.ref_resolution_n + 0.0  # no -0

    truth = {
        "t_sample": t_sample,
        "load": sample_load,
        "volts": volts,
        "force": np.stack([np.interp(t_sample, t, f_tissue[:, k]) for k in range(3)], axis=1),
        "phase": profile.phase[np.clip(np.round(t_sample / dt).astype(int), 0, t.size - 1)],
    }
    return TrialRecord(
        t_ms=np.round(t_host * 1e3, 3),
        counts=counts,
        t_s=t_ref,
        force=f_ref,
        clock_offset_s=offset,
        truth=truth,
    )
