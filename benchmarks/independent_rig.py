"""An independent rig simulator: writes `rig-log/1` batches from physics nobody tuned the pipeline on.

Written from the published facts only (docs/physics.md = [F], the paper, Tang et al. 2024 =
[paper]) and docs/rig-log-format.md; every other number is an assumption [A] of this module. It does
not import the pipeline. Everything is drawn from `seed`: the same seed writes the same bytes.

Frames. Reference (tissue) frame: z up, the robot's insertion plane at azimuth PSI = 60° [A] from the
F/T sensor's x axis. Insertion angle θ is the needle's tilt from vertical [A]; n = needle direction
(flange → tip), e1 = in-plane normal to n, e2 = out of plane. The reference records the force ON the
tissue; the needle feels its opposite, in its own tilted frame (n, e1, e2).

Needle-tissue force (Okamura et al. 2004 form [F]), integrated at 500 Hz [A]:
- robot: rest 1.5-2.5 s, 1 mm/s for 10 s, dwell 0.15-0.4 s, 2 mm/s back to the start, rest [F]/[A];
  0.1 s velocity ramps [A]; the tip starts 0.3-1.2 mm above the surface [A].
- before puncture a nonlinear spring a1·d + a2·d² (a1 = 0.05 N/mm, a2 = 0.02 N/mm² [A]) along the
  needle, its direction leaning toward the surface normal (n − 0.5·z, [A]) at oblique angles;
  puncture at 0.35 N (or 6 mm), the stored force then drops with τ = 60 ms [A].
- 35 % of points hold a deeper layer (4.5-7.5 mm, 0.1 N/mm, ruptures at 0.06-0.14 N) [A].
- cutting 0.12 N while advancing (builds in 50 ms, relaxes in 0.6 s when stopped) [A]; bevel
  side force 0.3 × cutting plus shaft bending 0.0008 N/mm² × L² along a unit-fixed bevel azimuth [A].
- friction on the shaft length L: Karnopp with an elastic tissue (stiffness 0.1 + 0.06·L N/mm):
  sticks in the dead band |v| < 0.02 mm/s (static 1.25 × Coulomb, relaxing with τ = 2.5 s), else
  saturates at Coulomb 0.035 N/mm (in) / 0.026 N/mm (out) plus viscous 0.004 N·s/mm² × L·|v| [A].
  Retraction drags the tissue up: the reference sees a pull that fades as the needle leaves [F].
- casts: E ~ N(97, 8) kPa [F: 97 kPa]; spring and rupture scale with E/97, cutting and friction
  with √(E/97) × N(1, 0.08-0.1) [A]. Points: each parameter × lognormal(σ = 0.12) [A].
- reference: ATI Nano17 in mN, 250 Hz DAQ [A], 3 mN white noise [F: a few mN], ±4 mN tare,
  1 mN 50 Hz pick-up, a 1 mN random walk, DAQ clock ±30 ppm [A]; its own clock, started within
  ±0.3 s (uniform) of the host logger's zero: trials.csv `ind_clock_offset_s` is that true offset
  at t_s = 0 (convention of docs/rig-log-format.md §7), `ind_session_s` the trial's session time.

Estimator [F, paper]: three FSRs at 120° (radius 5 mm [A], body 14 mm [F]) under silicone, loaded by
- the cast preload 0.49 N per FSR [F, read as per FSR so each sits mid-curve] × N(1, 0.10) [A];
- the axial load F·n, 70 % carried by the FSRs (the silicone ring the rest) [A], shared in thirds;
- moments: lateral tip force × 30 mm lever, the moving mass (8 g [A]) × 18 mm lever at sin θ, and the
  axial load × a needle offset (≈0.3 mm [A]); 35 % of a moment loads the FSRs [A], as
  (2M / 3r)·cos(azimuth): one FSR can unload [F]; the weight unloads them axially by cos θ.
- silicone creep: load − Σ g_k (load − lowpass_τk(load)), g = 0.10, 0.07 at τ = 0.35 s, 3.5 s [A].
- hysteresis: a play operator on the load, width 8-14 % of it [F: ~10 %]; rate independent.
- FSR law: R = R1·(1 N / F_e)^p + R_i, F_e = softplus(F − 0.2 N) [F: actuation 0.2 N], p ≈ 0.80
  [A, vs the datasheet's ∝ force], R1 = 28 kΩ [A, near 2·R_S = 34 kΩ·N [F]], R_i = 1.6-2.6 kΩ [F],
  open above 15 MΩ [F: > 10 MΩ]; conductance drift 1-4.5 % per decade of session time [F: < 5 %],
  repeatability ±1 % per trial [F: ±2 %], 0.3 % flicker (AR(1), ρ = 0.95) [A].
- read-out: transimpedance, 1.0 V drive, 47 kΩ feedback, 0.2 V offset, 1 kΩ known series resistor
  [A]; 12-bit ADC over 3.3 V [A], 0.4 mV + 0.5 LSB noise [A]; 30 Hz from a ceramic resonator
  (±1500 ppm) [A], host-stamped after 1.4 ms + exp(0.8 ms) latency, 2 % of samples 5-15 ms late,
  0.6 % lost, sometimes a burst of 2-5 [F: ms jitter, occasional loss].
Units differ (drawn per unit id): preload, R1 (±6 % [F]), p, actuation, R_i, hysteresis, drift, creep,
FSR azimuths (±4°), connector rotation (±20°), bevel azimuth, needle offset, axial and moment shares,
levers, moving mass, circuit tolerances (Rf ±0.5 %, offset ±4 mV, drive ±0.3 %) and the MCU clock.
Each batch re-mounts the unit (roll ±1.5°) and its preload has relaxed a little (±1.5 %) [A].

Batches (write_lab): `ind-cast<k>-<unit>` (training), `ind-heldout-<angle>deg-<unit>` (a cast not in
training; the first training unit and the new unit `ind-new-1`), `ind-calib-ind-new-1` (purpose:
calibration, yet another cast), and `ind-manifest.json` (the drawn units and casts) beside them.

Usage: `python benchmarks/independent_rig.py OUT_DIR [--training-units 1] [--casts 3] [--seed 7] ...`
"""

from __future__ import annotations

import argparse
import json
import shutil
import zlib
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from datetime import date, timedelta
from pathlib import Path
from typing import NamedTuple

import numpy as np
import yaml

DT = 0.002  # physics step, s
DAQ_HZ = 250.0
MCU_HZ = 30.0
PSI = np.deg2rad(60.0)
Z = np.array([0.0, 0.0, 1.0])
GRAVITY = 9.81
V_IN, V_OUT, INSERT_S, RAMP_S = 1.0, 2.0, 10.0, 0.1
ADC_BITS, VREF = 12, 3.3
FRONT_END = dict(circuit="transimpedance", drive_v=1.0, feedback_kohm=47.0, offset_v=0.2, series_kohm=1.0)
CHANNELS = ("fsr1", "fsr2", "fsr3")
ANGLES = (0, 15, 30, 45, 60, 75)
# tissue (N, mm, s)
A1, A2, RUPTURE, PUNCT_MAX, TAU_DROP, LEAN = 0.05, 0.02, 0.35, 6.0, 0.06, 0.5
CUT, TAU_CUT, TAU_TIP = 0.12, 0.05, 0.6
C_IN, C_OUT, STATIC, B_VISC, DV, K0, K1, TAU_TISSUE = 0.035, 0.026, 1.25, 0.004, 0.02, 0.1, 0.06, 2.5
BEVEL, BEND = 0.3, 0.0008
# estimator
R_OPEN, SOFT, SESSION_STEP_S = 15000.0, 0.025, 45.0  # kΩ, N, s between insertions


def rng_for(seed: int, *keys: object) -> np.random.Generator:
    return np.random.default_rng([seed, *(zlib.crc32(str(k).encode()) for k in keys)])


def frame(theta: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    h = np.array([np.cos(PSI), np.sin(PSI), 0.0])
    n = np.sin(theta) * h - np.cos(theta) * Z
    e1 = np.cos(theta) * h + np.sin(theta) * Z
    return n, e1, np.cross(Z, h)


@dataclass(frozen=True)
class Unit:
    unit_id: str
    preload: list[float]  # N per FSR
    r1_kohm: list[float]
    exponent: list[float]
    actuation: list[float]
    r_i_kohm: float
    hysteresis: list[float]
    drift: list[float]  # conductance change per decade of time
    creep_g: list[float]
    creep_tau: list[float]
    azimuth_deg: list[float]  # FSR directions, connector rotation included
    bevel_deg: float
    offset_mm: list[float]
    axial_share: list[float]
    moment_share: float
    radius_mm: float
    l_tip_mm: float
    l_cm_mm: float
    mass_g: float
    drive_v: float
    feedback_kohm: float
    offset_v: float
    mcu_ppm: float


def draw_unit(seed: int, unit_id: str) -> Unit:
    g = rng_for(seed, "unit", unit_id)

    def three(mean: float, rel: float) -> list[float]:
        return (mean * (1 + rel * g.standard_normal(3))).round(5).tolist()

    rotation = g.uniform(-20, 20)
    return Unit(
        unit_id=unit_id,
        preload=three(0.49, 0.10),
        r1_kohm=three(28.0, 0.06),
        exponent=np.clip(three(0.80, 0.05), 0.65, 0.93).tolist(),
        actuation=three(0.20, 0.15),
        r_i_kohm=round(g.uniform(1.6, 2.6), 4),
        hysteresis=g.uniform(0.08, 0.14, 3).round(4).tolist(),
        drift=g.uniform(0.01, 0.045, 3).round(4).tolist(),
        creep_g=[round(0.10 * g.lognormal(0, 0.2), 4), round(0.07 * g.lognormal(0, 0.2), 4)],
        creep_tau=[round(0.35 * g.lognormal(0, 0.2), 4), round(3.5 * g.lognormal(0, 0.2), 4)],
        azimuth_deg=(rotation + np.array([90.0, 210.0, 330.0]) + 4 * g.standard_normal(3)).round(3).tolist(),
        bevel_deg=round(g.uniform(0, 360), 2),
        offset_mm=(0.3 * g.standard_normal(2)).round(4).tolist(),
        axial_share=three(0.70, 0.08),
        moment_share=round(0.35 * (1 + 0.1 * g.standard_normal()), 4),
        radius_mm=round(5.0 * (1 + 0.03 * g.standard_normal()), 4),
        l_tip_mm=round(30.0 * (1 + 0.03 * g.standard_normal()), 3),
        l_cm_mm=round(18.0 * (1 + 0.1 * g.standard_normal()), 3),
        mass_g=round(8.0 * (1 + 0.1 * g.standard_normal()), 3),
        drive_v=round(1.0 * (1 + 0.003 * g.standard_normal()), 5),
        feedback_kohm=round(47.0 * (1 + 0.005 * g.standard_normal()), 4),
        offset_v=round(0.2 + 0.004 * g.standard_normal(), 5),
        mcu_ppm=round(1500 * g.standard_normal(), 1),
    )


@dataclass(frozen=True)
class Point:  # one insertion point of one cast
    a1: float
    a2: float
    rupture: float
    cut: float
    c_in: float
    c_out: float
    gap: float
    layer_depth: float
    layer_k: float
    layer_rupture: float


def cast_scales(seed: int, cast: int) -> tuple[float, float, float]:
    g = rng_for(seed, "cast", cast)
    e = float(np.clip(g.normal(97.0, 8.0), 75.0, 120.0)) / 97.0
    return e, np.sqrt(e) * g.normal(1, 0.08), np.sqrt(e) * g.normal(1, 0.1)  # stiffness, friction, cut


def draw_point(g: np.random.Generator, scales: tuple[float, float, float]) -> Point:
    se, sf, sc = scales
    v = g.lognormal(0.0, 0.12, 6)
    layer = g.random() < 0.35
    return Point(
        a1=A1 * se * v[0],
        a2=A2 * se * v[1],
        rupture=RUPTURE * se * v[2],
        cut=CUT * sc * v[3],
        c_in=C_IN * sf * v[4],
        c_out=C_OUT * sf * v[5],
        gap=g.uniform(0.3, 1.2),
        layer_depth=g.uniform(4.5, 7.5) if layer else np.inf,
        layer_k=0.1 * se,
        layer_rupture=g.uniform(0.06, 0.14) * se,
    )


def robot_path(g: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Velocity (mm/s) and travel along the needle (mm) on the physics grid."""
    segments = [
        (g.uniform(1.5, 2.5), 0.0),
        (INSERT_S, V_IN),
        (g.uniform(0.15, 0.4), 0.0),
        (INSERT_S * V_IN / V_OUT, -V_OUT),
        (g.uniform(1.0, 2.0), 0.0),
    ]
    v = np.concatenate([np.full(round(d / DT), s) for d, s in segments])
    k = round(RAMP_S / DT)
    v = np.convolve(v, np.ones(k) / k, mode="same")
    return v, np.cumsum(v) * DT


def tissue_force(theta: float, v: np.ndarray, x: np.ndarray, p: Point, bevel: float) -> np.ndarray:
    """Force of the needle on the tissue, (N, 3) in the reference frame, N."""
    n, e1, e2 = frame(theta)
    lean = n - LEAN * Z
    lean /= lean @ n  # its component along the needle is the spring force
    side = np.cos(bevel) * e1 + np.sin(bevel) * e2
    d = np.maximum(x - p.gap, 0.0)
    drop, stick = np.exp(-DT / TAU_DROP), np.exp(-DT / TAU_TISSUE)
    up, tip = 1 - np.exp(-DT / TAU_CUT), 1 - np.exp(-DT / TAU_TIP)
    spring, axial, lateral = (np.zeros(len(v)) for _ in range(3))
    punct = layer_done = False
    hold = hold2 = cut = fric = 0.0
    for k, (dk, vk) in enumerate(zip(d.tolist(), v.tolist(), strict=True)):
        if punct:
            hold *= drop
        else:
            hold = p.a1 * dk + p.a2 * dk * dk
            punct = hold >= p.rupture or dk >= PUNCT_MAX
        lay = 0.0
        if layer_done:
            hold2 *= drop
            lay = hold2
        elif punct and dk > p.layer_depth:
            lay = hold2 = p.layer_k * (dk - p.layer_depth)
            layer_done = lay >= p.layer_rupture
        target = p.cut if punct and vk > DV else 0.0
        cut += (target - cut) * (up if target > cut or vk < -DV else tip)
        length = dk if punct else 0.0
        if length <= 0.0:
            fric = 0.0
        else:
            trial = fric + (K0 + K1 * length) * vk * DT
            if vk > DV:  # slipping inward: Coulomb + viscous at most
                fric = min(trial, (p.c_in + B_VISC * vk) * length)
            elif vk < -DV:  # slipping outward: the tissue is lifted
                fric = max(trial, -(p.c_out - B_VISC * vk) * length)
            else:  # Karnopp dead band: stuck, the dragged tissue relaxes
                lim = STATIC * (p.c_in if trial > 0 else p.c_out) * length
                fric = min(max(trial * stick, -lim), lim)
        spring[k] = hold
        axial[k] = lay + cut + fric
        lateral[k] = BEVEL * cut + BEND * length * length
    return spring[:, None] * lean + axial[:, None] * n + lateral[:, None] * side


def fsr_loads(force: np.ndarray, theta: float, u: Unit, roll_deg: float, preload_scale: float) -> np.ndarray:
    """Normal load on each FSR (N, 3), N: preload, axial share, moments of tip force, weight, offset."""
    n, e1, e2 = frame(theta)
    weight = u.mass_g * 1e-3 * GRAVITY
    axial = force @ n - weight * np.cos(theta)  # compression of the estimator
    m1 = u.l_tip_mm * -(force @ e1) - u.l_cm_mm * weight * np.sin(theta) + axial * u.offset_mm[0]
    m2 = u.l_tip_mm * -(force @ e2) + axial * u.offset_mm[1]
    az = np.deg2rad(np.array(u.azimuth_deg) + roll_deg)
    proj = m1[:, None] * np.cos(az) + m2[:, None] * np.sin(az)
    share = np.array(u.axial_share) / 3
    return (
        np.array(u.preload) * preload_scale
        + share * axial[:, None]
        - u.moment_share * 2 / (3 * u.radius_mm) * proj
    )


def lowpass(x: np.ndarray, tau: float) -> np.ndarray:
    a, acc, out = np.exp(-DT / tau), float(x[0]), []
    for xk in x.tolist():
        acc = a * acc + (1 - a) * xk
        out.append(acc)
    return np.array(out)


def play(x: np.ndarray, width: float) -> np.ndarray:
    """Rate-independent hysteresis: the output lags the load by up to ± width/2 of it."""
    y, out = float(x[0]), []
    for xk in x.tolist():
        half = 0.5 * width * abs(xk)
        y = min(max(y, xk - half), xk + half)
        out.append(y)
    return np.array(out)


def fsr_conductance(loads: np.ndarray, u: Unit, t_session: np.ndarray, gain: np.ndarray) -> np.ndarray:
    """Conductance of each FSR (N, 3), 1/kΩ: creep in the silicone, hysteresis, power law, drift."""
    cols = []
    for i in range(3):
        f = loads[:, i]
        f = f - sum(g * (f - lowpass(f, tau)) for g, tau in zip(u.creep_g, u.creep_tau, strict=True))
        f = play(f, u.hysteresis[i])
        fe = np.maximum(SOFT * np.logaddexp(0.0, (f - u.actuation[i]) / SOFT), 1e-12)
        r = np.minimum(u.r1_kohm[i] * fe ** -u.exponent[i] + u.r_i_kohm, R_OPEN)
        cols.append(gain[i] * (1 + u.drift[i] * np.log10(1 + t_session / 10.0)) / r)
    return np.stack(cols, axis=1)


def host_samples(
    g: np.random.Generator, start: float, stop: float, ppm: float
) -> tuple[np.ndarray, np.ndarray]:
    """MCU sample instants (true time, s) and their host arrival times (s, before the host origin)."""
    period = (1 + ppm * 1e-6) / MCU_HZ
    tau = start + g.uniform(0, period) + period * np.arange(int((stop - start) / period))
    keep = g.random(len(tau)) >= 0.006
    if g.random() < 0.3:  # a USB hiccup loses a burst
        i = g.integers(10, len(tau) - 10)
        keep[i : i + g.integers(2, 6)] = False
    tau = tau[keep]
    late = np.where(g.random(len(tau)) < 0.02, g.uniform(5e-3, 15e-3, len(tau)), 0.0)
    arrive = tau + 1.4e-3 + g.exponential(0.8e-3, len(tau)) + late
    return tau, np.maximum.accumulate(arrive)


def simulate_trial(
    g: np.random.Generator, u: Unit, p: Point, angle: float, mount: tuple[float, float], t0_session: float
) -> tuple[str, str, float]:
    """One insertion: the .fsr.csv and .ref.csv texts and the true clock offset (s)."""
    theta = np.deg2rad(angle)
    v, x = robot_path(g)
    t = DT * np.arange(len(v))
    force = tissue_force(theta, v, x, p, np.deg2rad(u.bevel_deg))
    # clocks: host logger starts at tau_h, the DAQ at tau_h + offset
    offset, tau_h = g.uniform(-0.3, 0.3), g.uniform(0.3, 0.6)
    tau_r0, daq_ppm = tau_h + offset, 30 * g.standard_normal()
    # estimator
    loads = fsr_loads(force, theta, u, *mount)
    gain = 1 + 0.01 * g.standard_normal(3)
    cond = fsr_conductance(loads, u, t0_session + t, gain)
    tau, arrive = host_samples(g, tau_h, t[-1] - g.uniform(0.05, 0.3), u.mcu_ppm)
    c = np.stack([np.interp(tau, t, cond[:, i]) for i in range(3)], axis=1)
    flick = np.zeros_like(c)
    w = 0.003 * np.sqrt(1 - 0.95**2) * g.standard_normal(c.shape)
    for k in range(1, len(c)):
        flick[k] = 0.95 * flick[k - 1] + w[k]
    r = 1 / (c * (1 + flick)) + FRONT_END["series_kohm"]
    volts = u.offset_v + u.drive_v * u.feedback_kohm / r + 0.0004 * g.standard_normal(c.shape)
    full = 2**ADC_BITS - 1
    counts = np.clip(np.rint(volts / VREF * full + 0.5 * g.standard_normal(c.shape)), 0, full).astype(int)
    t_ms = np.round(1000 * (arrive - tau_h), 3)
    fsr = "t_ms," + ",".join(CHANNELS) + "\n"
    fsr += "".join(
        f"{tm:.3f},{a},{b},{cc}\n" for tm, (a, b, cc) in zip(t_ms.tolist(), counts.tolist(), strict=True)
    )
    # reference: force on the tissue in mN at the DAQ's instants
    n_ref = int((t[-1] - g.uniform(0.05, 0.3) - tau_r0) * DAQ_HZ)
    t_s = np.arange(n_ref) / DAQ_HZ
    tau_ref = tau_r0 + t_s / (1 + daq_ppm * 1e-6)
    ref = np.stack([np.interp(tau_ref, t, force[:, i]) for i in range(3)], axis=1) * 1000.0
    ref += g.normal(0, 4.0, 3) + 3.0 * g.standard_normal(ref.shape)
    ref += np.cumsum(g.standard_normal(ref.shape), axis=0) * (1.0 / np.sqrt(n_ref))
    ref += np.sin(2 * np.pi * 50.0 * tau_ref[:, None] + g.uniform(0, 2 * np.pi, 3))  # 1 mN mains pick-up
    text = "t_s,fx,fy,fz\n" + "".join(
        f"{ts:.4f},{fx:.2f},{fy:.2f},{fz:.2f}\n"
        for ts, (fx, fy, fz) in zip(t_s.tolist(), ref.tolist(), strict=True)
    )
    return fsr, text, offset


class Plan(NamedTuple):  # one batch to write
    batch_id: str
    unit: Unit
    cast: int
    angles: Sequence[float]
    per_angle: int
    role: str  # training, held-out, new-unit or calibration


def write_batch(out: Path, plan: Plan, *, seed: int, declare: bool, recorded: date) -> None:
    batch_id, unit, cast, angles, per_angle, role = plan
    folder = out / batch_id
    if folder.exists():
        meta = folder / "batch.yaml"
        if not (meta.is_file() and "independent_rig" in meta.read_text(encoding="utf-8")):
            raise FileExistsError(f"{folder} exists and was not written by independent_rig")
        shutil.rmtree(folder)
    folder.mkdir(parents=True)
    g = rng_for(seed, "batch", batch_id)
    mount = (float(g.normal(0, 1.5)), float(1 + 0.015 * g.standard_normal()))
    scales = cast_scales(seed, cast)
    order = [float(a) for a in g.permutation(np.array(angles, dtype=float))]
    rows = ["trial_id,angle_deg,tissue_point,unit_id,ind_clock_offset_s,ind_session_s"]
    trials = [(angle, k) for angle in order for k in range(1, per_angle + 1)]  # angle blocks, shuffled
    for i, (angle, k) in enumerate(trials):
        tid = f"ins{angle:g}-{k:02d}"
        tg = rng_for(seed, "trial", batch_id, tid)
        fsr, ref, offset = simulate_trial(tg, unit, draw_point(tg, scales), angle, mount, i * SESSION_STEP_S)
        (folder / f"{tid}.fsr.csv").write_text(fsr, encoding="utf-8")
        (folder / f"{tid}.ref.csv").write_text(ref, encoding="utf-8")
        point = f"c{cast}-{unit.unit_id}-{i + 1:03d}"
        rows.append(f"{tid},{angle:g},{point},{unit.unit_id},{offset:.4f},{i * SESSION_STEP_S:.0f}")
    (folder / "trials.csv").write_text("\n".join(rows) + "\n", encoding="utf-8")
    sensor: dict[str, object] = {
        "unit_id": unit.unit_id,
        "channels": list(CHANNELS),
        "units": "counts",
        "adc_bits": ADC_BITS,
        "vref_v": VREF,
    }
    if declare:
        sensor["front_end"] = dict(FRONT_END)
    meta = {
        "format": "rig-log/1",
        "batch_id": batch_id,
        "recorded": recorded,
        "purpose": "calibration" if role == "calibration" else "training",
        "tissue": {"material": "Ecoflex 00-30", "cast": cast, "notes": f"independent_rig cast {cast}"},
        "sensor": sensor,
        "reference": {"model": "ATI Nano17", "units": "mN", "frame": "tissue", "clock": "separate"},
        "robot": {"insertion_speed_mm_s": V_IN, "insertion_time_s": INSERT_S, "retraction_speed_mm_s": V_OUT},
        "generator": {"name": "independent_rig", "seed": seed, "role": role},
    }
    (folder / "batch.yaml").write_text(yaml.safe_dump(meta, sort_keys=False), encoding="utf-8")


def write_lab(
    out: Path,
    *,
    training_units: int = 1,
    casts: int = 3,
    trials_per_angle: int = 3,
    heldout_trials: int = 3,
    calibration_trials_per_angle: int = 1,
    seed: int = 7,
    declare: bool = True,
    angles: Sequence[float] = ANGLES,
) -> list[str]:
    """Write the lab's batches under `out`; returns their batch ids in the order written."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    units = [draw_unit(seed, f"ind-unit-{i}") for i in range(1, training_units + 1)]
    new = draw_unit(seed, "ind-new-1")
    day0 = date(2026, 2, 2)
    plan: list[Plan] = []
    for c in range(1, casts + 1):  # training casts, every angle, each recorded by every training unit
        plan += [Plan(f"ind-cast{c}-{u.unit_id}", u, c, angles, trials_per_angle, "training") for u in units]
    for u, role in ((units[0], "held-out"), (new, "new-unit")):  # a cast no training batch used
        plan += [
            Plan(f"ind-heldout-{a:g}deg-{u.unit_id}", u, casts + 1, [a], heldout_trials, role) for a in angles
        ]
    plan.append(
        Plan(f"ind-calib-{new.unit_id}", new, casts + 2, angles, calibration_trials_per_angle, "calibration")
    )
    for i, job in enumerate(plan):
        write_batch(
            out, job, seed=seed, declare=declare, recorded=day0 + timedelta(days=7 * job.cast + i % 7)
        )
    casts_drawn = {c: [float(s) for s in cast_scales(seed, c)] for c in range(1, casts + 3)}
    manifest = {
        "generator": "independent_rig",
        "seed": seed,
        "declare": declare,
        "batches": [p[0] for p in plan],
        "units": [asdict(u) for u in [*units, new]],
        "cast_scales_stiffness_friction_cut": casts_drawn,
    }
    (out / "ind-manifest.json").write_text(json.dumps(manifest, indent=1) + "\n", encoding="utf-8")
    return [p[0] for p in plan]


def main(argv: Sequence[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--training-units", type=int, default=1)
    ap.add_argument("--casts", type=int, default=3)
    ap.add_argument("--trials-per-angle", type=int, default=3)
    ap.add_argument("--heldout-trials", type=int, default=3)
    ap.add_argument("--calibration-trials-per-angle", type=int, default=1)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--no-declare", action="store_true", help="omit sensor.front_end from batch.yaml")
    ap.add_argument("--angles", default=",".join(map(str, ANGLES)))
    a = ap.parse_args(argv)
    angles = [float(s) if "." in s else int(s) for s in a.angles.split(",") if s.strip()]
    counts = {k: v for k, v in vars(a).items() if k not in ("out", "no_declare", "angles")}
    ids = write_lab(a.out, declare=not a.no_declare, angles=angles, **counts)
    print(f"wrote {len(ids)} batches to {a.out}")


if __name__ == "__main__":
    main()
