"""Trials fabricated for the signal-processing tests (`fabricate`), not taken from the simulator.

A needle force profile (nonlinear spring, puncture drop, friction, dwell relaxation, retraction
pull, exit) seen by an FSR tripod that is nonlinear (threshold + saturating conductance), partly
lagged (silicone creep: 30 % with a 1.5 s time constant), 10-bit quantised, host-stamped with
jitter and dropped samples; and by a reference sensor on its own clock with mN noise.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.signal import lfilter

from pipeline.config import ResampleParams
from pipeline.rig.repeats import SAMPLES_KEY, samples_sha256
from pipeline.signals.scaling import to_volts
from pipeline.signals.trial import ResampledTrial, Streams, align, check_response, on_grid

FSR_HZ = 30.0
REF_HZ = 100.0
FINE_DT = 0.001  # s: the fine grid the tactile sensor's force is made on
PARAMS = ResampleParams()
NEEDLE = np.array([0.4, 0.5, -0.77]) / np.linalg.norm([0.4, 0.5, -0.77])  # into the tissue
_E1 = np.cross(NEEDLE, [0.0, 0.0, 1.0])
E1 = _E1 / np.linalg.norm(_E1)
E2 = np.cross(NEEDLE, E1)


@dataclass
class Fabricated:
    """One fabricated trial as the rig would log it, plus its truth."""

    t_ms: np.ndarray  # host clock, jittered, some samples dropped
    counts: np.ndarray  # (n, channels), 10-bit ADC counts
    t_s: np.ndarray  # DAQ clock, uniform
    force: np.ndarray  # (m, 3), N
    offset_s: float  # reference stamp t_s happened at host time t_s + offset_s
    bounds: tuple[float, float, float, float]  # host times: insertion, dwell, retraction, exit

    def phase_at(self, t_host: np.ndarray) -> np.ndarray:
        """True phase at host times (force-based: rest before contact and after the exit)."""
        t0, t1, t2, t3 = self.bounds
        out = np.full(t_host.shape, "rest", dtype=object)
        out[(t_host >= t0) & (t_host < t1)] = "insertion"
        out[(t_host >= t1) & (t_host < t2)] = "dwell"
        out[(t_host >= t2) & (t_host < t3)] = "retraction"
        return out


def needle_force(
    t: np.ndarray, t0: float, dwell_s: float, puncture_mm: float | None
) -> tuple[np.ndarray, np.ndarray]:
    """Force along the needle (N) and the tip's share (drives the bevel's lateral force)."""
    t1, t2 = t0 + 10.0, t0 + 10.0 + dwell_s
    t3 = t2 + 5.0
    d = np.clip(t - t0, 0.0, 10.0)  # depth at 1 mm/s
    if puncture_mm is not None:  # nonlinear spring, rupture, then cutting + friction
        push = np.where(d < puncture_mm, 0.05 * d + 0.02 * d**2, 0.2 + 0.04 * d)
    else:
        push = 0.06 * d
    f1 = push[np.searchsorted(t, t1) - 1] if t1 <= t[-1] else 0.6
    relax = 1.0 - 0.2 * (1.0 - np.exp(-np.clip(t - t1, 0.0, None) / 0.5))
    f2 = f1 * (1.0 - 0.2 * (1.0 - np.exp(-dwell_s / 0.5)))
    tr = np.clip(t - t2, 0.0, None)
    unload = np.exp(-tr / 0.15)
    pull = np.minimum(0.25 * tr, 0.3)
    retract = f2 * unload - pull * (1.0 - unload)
    pull_end = min(0.25 * 5.0, 0.3)
    rebound = -pull_end * np.exp(-np.clip(t - t3, 0.0, None) / 0.1)
    f = np.select(
        [t < t0, t < t1, t < t2, t < t3],
        [0.0 * t, push, f1 * relax, retract],
        rebound,
    )
    tip = np.select([t < t0, t < t2, t < t3], [0.0 * t, f, f2 * unload], 0.0 * t)
    return f, tip


def fabricate(
    seed: int,
    offset_s: float,
    n_channels: int = 3,
    *,
    dwell_s: float = 0.8,
    puncture: bool = True,
    duration_s: float = 21.0,
    drop_p: float = 0.005,
    jitter_ms: float = 2.0,
) -> Fabricated:
    rng = np.random.default_rng(seed)
    dt = 0.001
    t = np.arange(-1.0, duration_s + 1.0, dt)  # host time, fine grid
    # Events fall anywhere between samples, as on a rig (a fixed phase would bias the test).
    rest_s = float(rng.uniform(1.5, 2.5))
    puncture_mm = float(rng.uniform(3.5, 5.0)) if puncture else None
    f, tip = needle_force(t, rest_s, dwell_s, puncture_mm)
    force = f[:, None] * NEEDLE + 0.15 * tip[:, None] * E1  # on the tissue, tissue frame
    force[t < 0] = 0.0

    # FSR tripod: axial share on all, lateral differentially, on a 0.49 N preload.
    az = np.radians(90.0 + 360.0 * np.arange(n_channels) / n_channels)
    load = (
        0.49
        + (force @ NEEDLE)[:, None] / 3
        + 1.05 * ((force @ E1)[:, None] * np.cos(az) + (force @ E2)[:, None] * np.sin(az))
    )
    a = np.exp(-dt / 1.5)  # silicone creep: 30 % of each change arrives with a 1.5 s lag
    lagged = lfilter([1 - a], [1, -a], load - load[0], axis=0) + load[0]
    load = np.clip(0.7 * load + 0.3 * lagged, 0.0, None)  # contact loss: no tension
    conductance = load / 34.0 / (1.0 + np.exp(-(load - 0.15) / 0.01))  # 1/kOhm, thresholded
    volts = 5.0 / (1.0 + (1.0 / (conductance + 1e-4) + 1.62) / 10.0)  # divider, R_M = 10 kOhm

    t_sample = np.arange(0.0, duration_s, 1.0 / FSR_HZ)
    keep = rng.random(t_sample.size) >= drop_p
    keep[[0, -1]] = True
    t_sample = t_sample[keep]
    v = np.stack([np.interp(t_sample, t, volts[:, k]) for k in range(n_channels)], axis=1)
    v += rng.normal(0.0, 0.0015, v.shape)
    counts = np.clip(np.round(v / 5.0 * 1023), 0, 1023)
    stamps = t_sample + rng.uniform(-jitter_ms, jitter_ms, t_sample.size) * 1e-3
    stamps = np.maximum.accumulate(stamps)

    t_s = np.arange(0.0, duration_s, 1.0 / REF_HZ)
    ref = np.stack([np.interp(t_s + offset_s, t, force[:, k]) for k in range(3)], axis=1)
    ref += rng.normal(0.0, 0.003, ref.shape)
    t1 = rest_s + 10.0
    bounds = (rest_s, t1, t1 + dwell_s, t1 + dwell_s + 5.0)
    return Fabricated(np.round(stamps * 1e3, 3), counts, t_s, ref, offset_s, bounds)


def volts_of(fab: Fabricated) -> np.ndarray:
    return to_volts(fab.counts, "counts", 10, 5.0)


def resample_streams(
    t_fsr_s: np.ndarray, volts: np.ndarray, t_ref_s: np.ndarray, force_n: np.ndarray, params: ResampleParams
) -> ResampledTrial:
    """One trial through the resample stage's own steps (`process_batch`) but the batch's judgement
    of a low quality: its response checked, aligned on its own reference, put on the grid. Raises
    SetAside."""
    streams = Streams(t_fsr_s, volts, t_ref_s, force_n)
    check_response(streams)
    return on_grid(streams, align(streams, streams, params), params)


def resample_fab(fab: Fabricated, params: ResampleParams = PARAMS) -> ResampledTrial:
    return resample_streams(fab.t_ms / 1e3, volts_of(fab), fab.t_s, fab.force, params)


def write_ingested(
    root: Path,
    batch_id: str,
    trials: dict[str, Fabricated],
    *,
    channels: list[str],
    units: str = "counts",
    ref_units: str = "N",
    angle: float = 30.0,
    with_truth: bool = True,
    purpose: str | None = None,
    clock: str | None = None,
    axes: tuple[str, ...] = ("fx", "fy", "fz"),
) -> Path:
    """An ingested batch folder as the ingest stage writes it (`purpose`, `clock` None: no such key;
    `axes`: the reference's recorded axes, batch.json's reference.axes when not all three)."""
    folder = root / batch_id
    folder.mkdir(parents=True)
    meta = {
        "format": "rig-log/1",
        "batch_id": batch_id,
        "sensor": {
            "unit_id": f"unit-{batch_id}",
            "channels": channels,
            "units": units,
            "adc_bits": 10 if units == "counts" else None,
            "vref_v": 5.0 if units == "counts" else None,
        },
        "reference": {"units": ref_units, "model": "fabricated"},
        "robot": None,
    }
    if purpose is not None:
        meta["purpose"] = purpose
    if clock is not None:
        meta["reference"]["clock"] = clock
    if axes != ("fx", "fy", "fz"):
        meta["reference"]["axes"] = list(axes)
    rows = {
        "trial_id": list(trials),
        "angle_deg": [angle] * len(trials),
        "tissue_point": ["p1"] * len(trials),
    }
    if with_truth:
        rows["sim_clock_offset_s"] = [f"{fab.offset_s:.6f}" for fab in trials.values()]
    pd.DataFrame(rows).to_parquet(folder / "trials.parquet")
    fsr, ref = [], []
    for tid, fab in trials.items():
        values = fab.counts if units == "counts" else volts_of(fab)
        fsr.append(
            pd.DataFrame({"trial_id": tid, "t_ms": fab.t_ms, **dict(zip(channels, values.T, strict=True))})
        )
        scale = 1e3 if ref_units == "mN" else 1.0
        ref.append(
            pd.DataFrame(
                {
                    "trial_id": tid,
                    "t_s": fab.t_s,
                    **{
                        a: f
                        for a, f in zip(["fx", "fy", "fz"], fab.force.T * scale, strict=True)
                        if a in axes
                    },
                }
            )
        )
    fsr_frame, ref_frame = pd.concat(fsr), pd.concat(ref)
    fsr_frame.to_parquet(folder / "fsr.parquet")
    ref_frame.to_parquet(folder / "ref.parquet")
    streams = [(fsr_frame, "t_ms"), (ref_frame, "t_s")]  # each trial's samples hash, as ingest keeps it
    meta[SAMPLES_KEY] = {tid: samples_sha256(streams, tid) for tid in trials}
    (folder / "batch.json").write_text(json.dumps(meta))
    return folder


def fabricate_tactile(
    seed: int, offset_s: float, *, duration_s: float = 20.0, rate_hz: float = 100.0
) -> Fabricated:
    """A trial of another kind of rig: a 4-channel tactile sensor at `rate_hz` beside the F/T sensor,
    pressed by hand a few times (smooth presses of random depth and timing, not an insertion). Its
    channels saturate (1 - exp(-load / 0.2 N)), half of each load change arrives through a 2 s creep,
    it lags by a backlash of 0.15 N, and it is noisy (60 mV): with the right files, the alignment's R² is
    far below the simulator's."""
    rng = np.random.default_rng(seed)
    t = np.arange(-1.0, duration_s + 1.0, FINE_DT)
    push = np.zeros_like(t)
    for start in np.sort(rng.uniform(1.0, duration_s - 4.0, 4)):
        width = rng.uniform(1.0, 2.5)
        inside = (t >= start) & (t < start + width)
        push[inside] += rng.uniform(0.5, 2.0) * np.sin(np.pi * (t[inside] - start) / width) ** 2
    shear = 0.3 * np.sin(2 * np.pi * t / rng.uniform(5.0, 9.0) + rng.uniform(0, 2 * np.pi)) * push
    return _tactile(rng, t, push, shear, offset_s, duration_s, rate_hz)


TACTILE = ["left", "right", "top", "bottom"]  # the tactile sensor's channels


def tactile_batch(seeds: range) -> dict[str, Fabricated]:
    """A batch of `fabricate_tactile` trials, one per seed (`t<seed>`), each with its own reference
    at an offset within ±0.2 s: the sensor's own lag (creep, backlash) adds up to about 0.2 s."""
    return {
        f"t{s:03d}": fabricate_tactile(s, float(np.random.default_rng(s).uniform(-0.2, 0.2))) for s in seeds
    }


def statuses(folder: Path) -> dict[str, dict]:
    """Each trial's row of the resample stage's offsets table for the ingested batch in `folder`
    (`write_ingested`), by trial id."""
    from pipeline.signals.resample import process_batch

    _, _, rows = process_batch(folder, PARAMS)
    return {r["trial_id"]: r for r in rows}


def swap_references(trials: dict[str, Fabricated], a: str, b: str) -> None:
    """Trials `a` and `b` with each other's reference file (in place)."""
    ta, tb = trials[a], trials[b]
    trials[a] = Fabricated(ta.t_ms, ta.counts, tb.t_s, tb.force, tb.offset_s, ta.bounds)
    trials[b] = Fabricated(tb.t_ms, tb.counts, ta.t_s, ta.force, ta.offset_s, tb.bounds)


def fabricate_presses(
    seed: int, offset_s: float, *, start_s: float = 0.0, duration_s: float = 8.0
) -> Fabricated:
    """A cut of a longer recording, as a public tactile data set gives it: a 4-channel sensor pressed
    again and again at a steady pace (every 1.2 to 1.8 s, similar depths), so that any other cut's
    reference lines up with it a little; saturating, creeping, hysteretic (0.15 N backlash) and
    noisy. Both streams carry the recording's time from `start_s` (the reference's `offset_s` behind
    on its own clock; 0 for one clock)."""
    rng = np.random.default_rng(seed)
    t = np.arange(-1.0, duration_s + 1.0, FINE_DT)
    push = np.zeros_like(t)
    period = rng.uniform(1.2, 1.8)
    start = rng.uniform(-0.5 * period, 0.5 * period)
    while start < duration_s:
        width = period * rng.uniform(0.5, 0.7)
        inside = (t >= start) & (t < start + width)
        push[inside] += rng.uniform(1.0, 1.4) * np.sin(np.pi * (t[inside] - start) / width) ** 2
        start += period * rng.uniform(0.95, 1.05)
    shear = 0.2 * push * np.sin(2 * np.pi * t / rng.uniform(5.0, 9.0))
    return _tactile(rng, t, push, shear, offset_s, duration_s, 100.0, start_s)


def _tactile(
    rng: np.random.Generator,
    t: np.ndarray,
    push: np.ndarray,
    shear: np.ndarray,
    offset_s: float,
    duration_s: float,
    rate_hz: float,
    start_s: float = 0.0,
) -> Fabricated:
    """What the 4-channel tactile sensor and the F/T sensor log of a pressing force (`push` normal,
    `shear` lateral, N, on the fine grid `t`, FINE_DT apart): saturating channels, half of each load
    change through a 2 s creep, a 0.15 N backlash, 60 mV of noise; both streams in the recording's
    time from `start_s`, the reference `offset_s` behind."""
    force = np.stack([shear, 0.5 * shear, -push], axis=1)  # on the tissue, tissue frame
    az = np.radians(45.0 + 90.0 * np.arange(4))
    load = push[:, None] / 4 + 0.8 * (shear[:, None] * np.cos(az) + 0.5 * shear[:, None] * np.sin(az))
    a = np.exp(-FINE_DT / 2.0)
    lagged = lfilter([1 - a], [1, -a], load - load[0], axis=0) + load[0]
    load = np.clip(0.5 * load + 0.5 * lagged, 0.0, None)
    # hysteresis (backlash, the silicone's friction): a channel's load lags the true one by up to
    # 0.15 N, following it only once it has moved that far in the new direction
    held = np.empty_like(load)
    h = load[0].copy()
    for i, row in enumerate(load):
        h = np.clip(h, row - 0.15, row)
        held[i] = h
    volts = 4.5 * (1.0 - np.exp(-held / 0.2))
    t_sample = np.arange(0.0, duration_s, 1.0 / rate_hz)
    v = np.stack([np.interp(t_sample, t, volts[:, k]) for k in range(4)], axis=1)
    v += rng.normal(0.0, 0.06, v.shape)
    counts = np.clip(np.round(v / 5.0 * 1023), 0, 1023)
    t_s = np.arange(0.0, duration_s, 1.0 / REF_HZ)
    ref = np.stack([np.interp(t_s + offset_s, t, force[:, k]) for k in range(3)], axis=1)
    ref += rng.normal(0.0, 0.01, ref.shape)
    return Fabricated(
        np.round((t_sample + start_s) * 1e3, 3), counts, t_s + start_s, ref, offset_s, (0.0,) * 4
    )
