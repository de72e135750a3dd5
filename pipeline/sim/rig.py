"""The built-in rig simulator: writes rig-log/1 batches (`docs/rig-log-format.md`) from the physics
in `pipeline.sim.physics` (`docs/physics.md`), standing in for a lab on a machine with none attached.

Layout, sized like the paper: `train_batches` tissue casts, each recorded at every angle on
`trials_per_angle` tissue points (about 11k samples per angle at 30 Hz), plus one held-out batch
per angle (the paper's "new dataset"), named `sim-heldout-<angle>deg`. All batches use one
estimator unit, as in the paper. Seeded: the same params give the same bytes.
"""

from __future__ import annotations

import json
import shutil
import sys
import zlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from datetime import date, timedelta
from pathlib import Path

import numpy as np
import yaml

from pipeline.config import EffectScales, SimulateParams
from pipeline.rig.format import (
    BATCH_FILE,
    FORMAT,
    FSR_TIME,
    REF_COLUMNS,
    TRIAL_COLUMNS,
    TRIALS_FILE,
    fsr_file,
    ref_file,
)
from pipeline.sim import physics
from pipeline.vocab import angle_name

MANIFEST = "simulate.json"
CHANNELS = ("fsr1", "fsr2", "fsr3")

Log = Callable[[str], None]


def _stderr(msg: str) -> None:
    print(msg, file=sys.stderr)


@dataclass(frozen=True)
class BatchPlan:
    """One simulated batch: which angles, how many tissue points each, and its seed key."""

    batch_id: str
    number: int
    angles_deg: tuple[float, ...]
    trials_per_angle: int


def plan_batches(p: SimulateParams) -> list[BatchPlan]:
    """Training casts (every angle) then one held-out cast per angle."""
    plans = [
        BatchPlan(f"sim-tissue-{b}", b, p.angles_deg, p.trials_per_angle)
        for b in range(1, p.train_batches + 1)
    ]
    for i, angle in enumerate(p.angles_deg):
        plans.append(
            BatchPlan(
                f"sim-heldout-{angle_name(angle)}deg",
                p.train_batches + 1 + i,
                (angle,),
                p.heldout_trials_per_angle,
            )
        )
    return [b for b in plans if b.trials_per_angle > 0]


def _rng(p: SimulateParams, *key: int) -> np.random.Generator:
    # One stream per key: a batch or trial draws the same numbers whatever else is simulated.
    return np.random.default_rng([p.seed, *key])


def draw_tissue(rng: np.random.Generator, cast_scale: float, effects: EffectScales) -> physics.Tissue:
    """One tissue point of one cast: casts differ in stiffness, points within a cast too."""
    s = effects.tissue_inhomogeneity
    base = physics.Tissue()

    def vary(value: float, sigma: float = 0.15) -> float:
        return value * float(np.exp(s * rng.normal(0.0, sigma)))

    return physics.Tissue(
        gap_mm=float(1.0 + s * rng.uniform(-0.5, 0.5)),
        a1_n_mm=vary(base.a1_n_mm) * cast_scale,
        a2_n_mm2=vary(base.a2_n_mm2) * cast_scale,
        puncture_mm=float(base.puncture_mm + s * rng.normal(0.0, 0.6)),
        cutting_n=vary(base.cutting_n) * cast_scale,
        friction_in_n_mm=vary(base.friction_in_n_mm) * cast_scale,
        friction_out_n_mm=vary(base.friction_out_n_mm) * cast_scale,
        grip_n=vary(base.grip_n),
        tent_n_mm=vary(base.tent_n_mm) * cast_scale,
        bevel_deg=float(base.bevel_deg + s * rng.normal(0.0, 10.0)),
    )


def draw_motion(rng: np.random.Generator) -> physics.Motion:
    """The robot programme is fixed; when the operator starts and stops recording is not."""
    return physics.Motion(
        rest_before_s=float(rng.uniform(1.5, 2.5)),
        dwell_s=float(rng.uniform(0.5, 1.0)),
        rest_after_s=float(rng.uniform(2.0, 3.0)),
    )


def simulate_batch(p: SimulateParams, plan: BatchPlan) -> Iterator[tuple[dict, physics.TrialRecord]]:
    """Yield (trial row, record) for every trial of one batch, in recording order."""
    est = physics.draw_estimator(_rng(p, zlib.crc32(p.unit_id.encode())), p.effects)
    batch_rng = _rng(p, 1, plan.number)
    # Ecoflex 00-30 casts differ batch to batch (E about 97 kPa nominal).
    cast_scale = float(np.exp(p.effects.batch_variation * batch_rng.normal(0.0, 0.10)))
    clocks = physics.Clocks(fsr_rate_hz=p.fsr_rate_hz, ref_rate_hz=p.ref_rate_hz)
    for a, angle in enumerate(plan.angles_deg):
        for k in range(1, plan.trials_per_angle + 1):
            rng = _rng(p, 2, plan.number, a, k)
            tissue = draw_tissue(rng, cast_scale, p.effects)
            record = physics.simulate_trial(
                angle, tissue, est, p.effects, clocks, rng, motion=draw_motion(rng)
            )
            row = {
                "trial_id": f"a{angle_name(angle)}-t{k:02d}",
                "angle_deg": angle_name(angle),
                "tissue_point": f"p{a + 1:02d}-{k:02d}",
                "sim_clock_offset_s": f"{record.clock_offset_s:.6f}",
            }
            yield row, record


def batch_yaml(p: SimulateParams, plan: BatchPlan) -> dict:
    """batch.yaml of one simulated batch (unknown keys such as `simulator` are kept by ingest)."""
    return {
        "format": FORMAT,
        "batch_id": plan.batch_id,
        "recorded": (date(2026, 11, 2) + timedelta(days=plan.number)).isoformat(),
        "tissue": {"material": "Ecoflex 00-30", "notes": "simulated cast (needlecue simulate)"},
        "sensor": {
            "unit_id": p.unit_id,
            "channels": list(CHANNELS),
            "units": "counts" if p.effects.adc else "volts",
            "adc_bits": physics.Estimator.adc_bits,
            "vref_v": physics.Estimator.vref_v,
        },
        "reference": {"model": "ATI Nano17 (simulated)", "units": "N", "frame": "tissue"},
        "robot": {"insertion_speed_mm_s": 1.0, "insertion_time_s": 10.0, "retraction_speed_mm_s": 2.0},
        "simulator": {"seed": p.seed, "role": "held-out" if "heldout" in plan.batch_id else "training"},
    }


def write_batch(p: SimulateParams, plan: BatchPlan, out_dir: Path) -> int:
    """Write one batch folder; returns the number of estimator samples written."""
    folder = out_dir / plan.batch_id
    folder.mkdir(parents=True)
    rows, n_samples = [], 0
    integer = p.effects.adc
    for row, rec in simulate_batch(p, plan):
        rows.append(row)
        fsr = np.column_stack([rec.t_ms, rec.counts])
        fmt = ["%.3f"] + (["%d"] if integer else ["%.5f"]) * len(CHANNELS)
        _savetxt(folder / fsr_file(row["trial_id"]), fsr, fmt, (FSR_TIME, *CHANNELS))
        ref = np.column_stack([rec.t_s, rec.force])
        _savetxt(folder / ref_file(row["trial_id"]), ref, ["%.5f"] * len(REF_COLUMNS), REF_COLUMNS)
        n_samples += rec.t_ms.size
    with (folder / BATCH_FILE).open("w") as f:
        yaml.safe_dump(batch_yaml(p, plan), f, sort_keys=False)
    header = list(rows[0]) if rows else list(TRIAL_COLUMNS)
    lines = [",".join(header)] + [",".join(r[c] for c in header) for r in rows]
    (folder / TRIALS_FILE).write_text("\n".join(lines) + "\n")
    return n_samples


def _savetxt(path: Path, data: np.ndarray, fmt: list[str], header: tuple[str, ...]) -> None:
    np.savetxt(path, data, fmt=fmt, delimiter=",", header=",".join(header), comments="")


def prepare_out_dir(out_dir: Path) -> None:
    """Make `out_dir` empty, refusing to clear anything the simulator did not write."""
    if out_dir.exists() and any(out_dir.iterdir()):
        if not (out_dir / MANIFEST).is_file():
            raise FileExistsError(
                f"{out_dir} is not empty and was not written by the simulator ({MANIFEST} missing); "
                "choose an empty or new folder"
            )
        shutil.rmtree(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)


def run(p: SimulateParams, out_dir: Path, *, log: Log = _stderr) -> list[str]:
    """Write all planned batches (or none when disabled) and the manifest; return batch ids."""
    prepare_out_dir(out_dir)
    written = []
    if p.enabled:
        for plan in plan_batches(p):
            n = write_batch(p, plan, out_dir)
            written.append(plan.batch_id)
            log(
                f"simulate: {plan.batch_id}: {len(plan.angles_deg) * plan.trials_per_angle} trials, "
                f"{n} estimator samples"
            )
    manifest = {"generator": "needlecue simulate", "params": p.model_dump(mode="json"), "batches": written}
    (out_dir / MANIFEST).write_text(json.dumps(manifest, indent=2, sort_keys=True) + "\n")
    return written


def write_new_batch(
    p: SimulateParams, raw_dir: Path, batch_id: str, angles_deg: tuple[float, ...], trials_per_angle: int
) -> int:
    """One more simulated tissue cast, as a lab would drop it into `raw_dir`: a new batch folder
    (refused if it exists), recorded with the same estimator unit, its cast and tissue points
    seeded by its id. Returns the number of estimator samples written."""
    if (raw_dir / batch_id).exists():
        raise FileExistsError(f"{raw_dir / batch_id} exists: choose a new batch id")
    # numbers 1..1000 are plan_batches' own casts; an id-derived number above them is a new cast
    number = 1000 + zlib.crc32(batch_id.encode()) % 1_000_000
    plan = BatchPlan(batch_id, number, tuple(angles_deg), trials_per_angle)
    raw_dir.mkdir(parents=True, exist_ok=True)
    return write_batch(p, plan, raw_dir)
