"""The resample stage: units, clock offset, anti-alias filter, grid, gaps, phases, outputs.

Data are fabricated here (`fabricate`), not taken from the simulator: a needle force profile
(nonlinear spring, puncture drop, friction, dwell relaxation, retraction pull, exit) seen by
an FSR tripod that is nonlinear (threshold + saturating conductance), partly lagged
(silicone creep: 30 % with a 1.5 s time constant), 10-bit quantised, host-stamped with
jitter and dropped samples; and by a reference sensor on its own clock with mN noise.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest
from scipy.signal import lfilter

from pipeline import resample as rs
from pipeline.config import ResampleParams

FSR_HZ = 30.0
REF_HZ = 100.0
PARAMS = ResampleParams()
NEEDLE = np.array([0.4, 0.5, -0.77]) / np.linalg.norm([0.4, 0.5, -0.77])  # into the tissue
_E1 = np.cross(NEEDLE, [0.0, 0.0, 1.0])
E1 = _E1 / np.linalg.norm(_E1)
E2 = np.cross(NEEDLE, E1)


# --------------------------------------------------------------------------- fabrication
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
    return rs.to_volts(fab.counts, "counts", 10, 5.0)


def resample_fab(fab: Fabricated, params: ResampleParams = PARAMS) -> rs.ResampledTrial:
    return rs.resample_trial(fab.t_ms / 1e3, volts_of(fab), fab.t_s, fab.force, params)


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
) -> Path:
    """An ingested batch folder as the ingest stage writes it."""
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
    (folder / "batch.json").write_text(json.dumps(meta))
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
                    **dict(zip(["fx", "fy", "fz"], fab.force.T * scale, strict=True)),
                }
            )
        )
    pd.concat(fsr).to_parquet(folder / "fsr.parquet")
    pd.concat(ref).to_parquet(folder / "ref.parquet")
    return folder


# --------------------------------------------------------------------------- units
def test_counts_become_volts_and_millinewtons_become_newtons():
    # Given 10-bit counts over a 5 V reference, and forces in mN
    counts = np.array([0.0, 511.5, 1023.0])
    # When converted
    volts = rs.to_volts(counts, "counts", 10, 5.0)
    newtons = rs.to_newtons(np.array([250.0, -1000.0]), "mN")
    # Then full scale is vref, volts and N pass through unchanged
    np.testing.assert_allclose(volts, [0.0, 2.5, 5.0])
    np.testing.assert_allclose(newtons, [0.25, -1.0])
    np.testing.assert_array_equal(rs.to_volts(volts, "volts", None, None), volts)
    np.testing.assert_array_equal(rs.to_newtons(newtons, "N"), newtons)
    with pytest.raises(ValueError):
        rs.to_volts(counts, "counts", None, 5.0)
    with pytest.raises(ValueError):
        rs.to_newtons(newtons, "kN")


# --------------------------------------------------------------------------- clock offset
@pytest.mark.parametrize(
    ("offset_s", "n_channels"),
    [(0.23, 3), (-0.31, 3), (0.0, 3), (0.17, 1), (-0.12, 1), (0.36, 5), (-0.27, 5)],
)
def test_offset_is_recovered_within_one_fsr_sample(offset_s, n_channels):
    # Given a trial with a known clock offset and a nonlinear, lagged, quantised FSR response
    fab = fabricate(seed=abs(round(1000 * offset_s)) + n_channels, offset_s=offset_s, n_channels=n_channels)
    # When the offset is estimated from the signals alone
    est = rs.estimate_offset(fab.t_ms / 1e3, volts_of(fab), fab.t_s, fab.force, 0.5, 0.002)
    # Then it is within one estimator sample period of the truth, with a clear fit
    assert abs(est.offset_s - offset_s) < 1.0 / FSR_HZ, est
    assert not est.on_edge
    assert 0.3 < est.quality <= 1.0


def test_offset_outside_the_search_window_is_set_aside():
    # Given a clock offset larger than the search window
    fab = fabricate(seed=5, offset_s=0.45)
    narrow = PARAMS.model_copy(update={"max_offset_s": 0.2})
    # When the trial is resampled, then it is set aside with the reason, not silently misaligned
    with pytest.raises(rs.SetAside, match="edge of the"):
        resample_fab(fab, narrow)


def test_too_little_overlap_is_set_aside():
    # Given a reference stream of only 0.4 s
    fab = fabricate(seed=6, offset_s=0.1)
    keep = fab.t_s < 0.4
    # When the offset is estimated, then the trial is set aside
    with pytest.raises(rs.SetAside, match="overlap"):
        rs.estimate_offset(fab.t_ms / 1e3, volts_of(fab), fab.t_s[keep], fab.force[keep], 0.5, 0.002)


# --------------------------------------------------------------------------- filter, grid, gaps
def _amplitude(t: np.ndarray, x: np.ndarray, hz: float) -> float:
    """Amplitude of the `hz` component of x(t), by least squares on sin/cos (+ mean)."""
    design = np.stack([np.sin(2 * np.pi * hz * t), np.cos(2 * np.pi * hz * t), np.ones_like(t)], axis=1)
    coef, *_ = np.linalg.lstsq(design, x, rcond=None)
    return float(np.hypot(coef[0], coef[1]))


def test_anti_alias_filter_removes_a_tone_above_the_target_nyquist():
    # Given a 100 Hz stream: a slow 0.5 Hz signal plus a 20 Hz tone (above 15 Hz, the 30 Hz grid's Nyquist)
    t = np.arange(0.0, 20.0, 0.01)
    x = np.sin(2 * np.pi * 0.5 * t) + 0.5 * np.sin(2 * np.pi * 20.0 * t)
    grid = np.arange(2.0, 18.0, 1.0 / 30.0)
    # When it is resampled onto the 30 Hz grid with, and naively without, the anti-alias filter
    filtered = rs.resample_stream(t, x, grid, 30.0, 4)
    naive = np.interp(grid, t, x)
    # Then naive decimation folds the tone to 10 Hz; the filtered stream keeps almost none of it
    alias_naive, alias_filtered = _amplitude(grid, naive, 10.0), _amplitude(grid, filtered, 10.0)
    assert alias_naive > 0.3
    assert alias_filtered < 0.02
    # And the slow signal passes unchanged
    assert _amplitude(grid, filtered, 0.5) == pytest.approx(1.0, abs=0.01)


@pytest.mark.parametrize("rate_hz", [30.0, 20.0])
def test_grid_is_uniform_at_rate_hz_and_starts_at_zero(rate_hz):
    # Given a fabricated trial
    fab = fabricate(seed=7, offset_s=-0.15, drop_p=0.0)
    # When it is resampled at rate_hz
    res = resample_fab(fab, PARAMS.model_copy(update={"rate_hz": rate_hz}))
    # Then t_s runs 0, 1/rate, 2/rate, ... and both streams are on it
    n = res.t_s.size
    np.testing.assert_array_equal(res.t_s, np.arange(n) / rate_hz)
    assert res.volts.shape == (n, 3) and res.force_n.shape == (n, 3)
    assert n >= (21.0 - 0.15 - 0.1) * rate_hz - 2


def test_gap_mask_marks_only_points_inside_long_gaps():
    # Given samples with a 0.5 s hole and a 0.1 s hole
    t_src = np.array([0.0, 0.1, 0.2, 0.7, 0.8, 0.9])
    query = np.array([0.15, 0.2, 0.3, 0.5, 0.7, 0.75])
    # When the gap mask is computed for max_gap 0.25 s
    mask = rs.gap_mask(t_src, query, 0.25)
    # Then only the points strictly inside the 0.5 s hole are in a gap
    np.testing.assert_array_equal(mask, [False, False, True, True, False, False])


def test_grid_points_in_a_long_gap_are_dropped():
    # Given a trial whose estimator stream lost 0.6 s (8.0 - 8.6 s host time)
    fab = fabricate(seed=8, offset_s=0.05, drop_p=0.0)
    hole = (fab.t_ms >= 8000) & (fab.t_ms < 8600)
    fab.t_ms, fab.counts = fab.t_ms[~hole], fab.counts[~hole]
    # When it is resampled
    res = resample_fab(fab)
    # Then the grid points inside the gap are gone, and counted
    t_host = res.t_s + res.t0_host_s
    assert not np.any((t_host > 8.0) & (t_host < 8.59))
    assert 17 <= res.n_dropped_gap <= 20  # 0.63 s between the samples either side, at 30 Hz
    # And the 33 ms gaps of single dropped samples are not gaps
    fab2 = fabricate(seed=8, offset_s=0.05, drop_p=0.05)
    assert resample_fab(fab2).n_dropped_gap == 0


# --------------------------------------------------------------------------- phases
def _runs(labels: np.ndarray) -> list[str]:
    return [str(x) for i, x in enumerate(labels) if i == 0 or labels[i - 1] != x]


@pytest.mark.parametrize(
    ("dwell_s", "puncture", "expected"),
    [
        (0.8, True, ["rest", "insertion", "dwell", "retraction", "rest"]),
        (1.0, False, ["rest", "insertion", "dwell", "retraction", "rest"]),
        (0.0, True, None),  # no dwell: it must not crash, and the order must hold
    ],
)
def test_phase_labels_match_the_truth_and_come_in_order(dwell_s, puncture, expected):
    # Given a fabricated trial with a known phase sequence
    fab = fabricate(seed=11, offset_s=0.12, dwell_s=dwell_s, puncture=puncture)
    # When it is resampled and labelled
    res = resample_fab(fab)
    truth = fab.phase_at(res.t_s + res.t0_host_s)
    # Then most samples carry the true phase
    assert np.mean(res.phase == truth) >= 0.9
    # And phases appear in the order rest -> insertion -> dwell -> retraction -> rest
    runs = _runs(res.phase)
    order = ["rest", "insertion", "dwell", "retraction", "rest"]
    it = iter(order)
    assert all(any(r == o for o in it) for r in runs), runs
    if expected:
        assert runs == expected


def test_phase_labels_without_any_force_or_without_a_pull():
    # Given a trial with no force at all, and a profile with no pull on retraction
    rate = 30.0
    t = np.arange(0.0, 15.0, 1 / rate)
    rng = np.random.default_rng(3)
    flat = rng.normal(0, 0.003, (t.size, 3))
    bump = np.where((t > 2) & (t < 10), np.sin(np.pi * (t - 2) / 8), 0.0)[:, None] * [0.2, 0.3, 0.5] + flat
    # When labelled
    none, no_pull = rs.label_phases(flat, rate), rs.label_phases(bump, rate)
    # Then the quiet trial is rest throughout, and the other keeps the order without crashing
    assert set(none) == {"rest"}
    assert _runs(no_pull)[0] == "rest" and "insertion" in set(no_pull)
    assert set(no_pull) <= set(rs.PHASES)


# --------------------------------------------------------------------------- the stage
def test_stage_writes_deterministic_outputs_and_reports(tmp_path):
    # Given two ingested batches (counts + N with a known truth; volts + mN, one channel, no truth),
    # a set-aside batch folder without trials.parquet, and a trial whose reference is too short
    ingested = tmp_path / "ingested"
    short = fabricate(seed=21, offset_s=0.1)
    short.t_s, short.force = short.t_s[:40], short.force[:40]
    write_ingested(
        ingested,
        "bench-a",
        {"t1": fabricate(seed=22, offset_s=0.21), "t2": fabricate(seed=23, offset_s=-0.26), "t3": short},
        channels=["fsr1", "fsr2", "fsr3"],
    )
    write_ingested(
        ingested,
        "bench-b",
        {"u1": fabricate(seed=24, offset_s=0.05, n_channels=1)},
        channels=["v0"],
        units="volts",
        ref_units="mN",
        angle=45.0,
        with_truth=False,
    )
    (ingested / "rejected").mkdir()
    (ingested / "rejected" / "problems.json").write_text("[]")
    params = tmp_path / "params.yaml"
    params.write_text("resample:\n  rate_hz: 30.0\n")

    # When the stage runs twice into two folders
    for k in (1, 2):
        rs.main(ingested, tmp_path / f"out{k}", tmp_path / f"rep{k}", params)

    # Then the outputs are byte-identical
    out1, out2 = tmp_path / "out1", tmp_path / "out2"
    names = sorted(p.name for p in out1.iterdir())
    assert names == ["bench-a.json", "bench-a.parquet", "bench-b.json", "bench-b.parquet"]
    for name in names:
        assert (out1 / name).read_bytes() == (out2 / name).read_bytes()
    assert (tmp_path / "rep1/offsets.csv").read_bytes() == (tmp_path / "rep2/offsets.csv").read_bytes()

    # And each batch keeps its channel names, in volts and newtons, with the documented columns
    a = pq.read_table(out1 / "bench-a.parquet").to_pandas()
    assert list(a.columns) == [*rs.ID_COLUMNS, "fsr1", "fsr2", "fsr3", "fx", "fy", "fz"]
    assert sorted(a.trial_id.unique()) == ["t1", "t2"]
    assert a[["fsr1", "fsr2", "fsr3"]].max().max() < 5.0
    b = pq.read_table(out1 / "bench-b.parquet").to_pandas()
    assert list(b.columns) == [*rs.ID_COLUMNS, "v0", "fx", "fy", "fz"]
    assert b[["fx", "fy", "fz"]].abs().max().max() < 2.0  # N, not mN
    assert (b.angle_deg == 45.0).all() and set(b.phase) <= set(rs.PHASES)
    meta = json.loads((out1 / "bench-b.json").read_text())
    assert meta == {"batch_id": "bench-b", "channels": ["v0"], "rate_hz": 30.0, "unit_id": "unit-bench-b"}

    # And the offsets report has one row per trial, the truth where known, the reason where set aside
    rep = pd.read_csv(tmp_path / "rep1/offsets.csv", dtype=str, keep_default_na=False).set_index("trial_id")
    assert list(rep.index) == ["t1", "t2", "t3", "u1"]
    assert (rep.loc[["t1", "t2", "u1"], "status"] == "ok").all()
    assert rep.loc["t3", "status"].startswith("set aside: ")
    assert abs(float(rep.loc["t1", "error_s"])) < 1 / 30 and abs(float(rep.loc["t2", "error_s"])) < 1 / 30
    assert rep.loc["u1", "true_offset_s"] == "" and rep.loc["u1", "error_s"] == ""
    assert int(rep.loc["t1", "n_grid"]) == int((a.trial_id == "t1").sum())
    summary = (tmp_path / "rep1/summary.md").read_text()
    assert "4 (3 ok, 1 set aside)" in summary and "Offset error" in summary
    assert (tmp_path / "rep1/offsets.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
