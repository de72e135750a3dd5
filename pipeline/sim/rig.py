"""The built-in rig simulator: writes rig-log/1 batches (`docs/rig-log-format.md`) from the physics
in `pipeline.sim.physics` (`docs/physics.md`), standing in for a lab on a machine with none attached.

Layout (`plan_batches`); a batch is one tissue cast recorded by one estimator unit:

- training: `sim-tissue-<cast>-<unit>`, each of `train_batches` casts recorded at every angle by
  each training unit of `units`, `trials_per_angle` tissue points per angle (3 casts x 3 units x 3
  trials = 27 trials, about 16k samples, per angle at 30 Hz). The units recording one cast share
  its stiffness; their tissue points differ;
- same-unit held-out (the paper's "new dataset"): `sim-heldout-<angle>deg`, one more cast per
  angle, `heldout_trials_per_angle` trials, recorded by a training unit (`units[i % len(units)]`);
- new-unit held-out: `sim-heldout-<angle>deg-<unit>`, another cast per angle and unit of
  `new_units` (units never seen in training), as many trials;
- calibration: `sim-calib-<unit>` per new unit, its own cast, `calibration_trials_per_angle`
  trials at every angle (about 20 s of robot time per trial), `purpose: calibration` in its
  batch.yaml, so the split keeps its trials out of train/val/test/external.

Every unit is drawn from its id (`physics.draw_estimator`), so a unit is the same in every batch
and every run with the same seed; `simulate.json` lists the drawn units. Seeded: the same params
give the same bytes.
"""

from __future__ import annotations

import itertools
import json
import logging
import shutil
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import date, timedelta
from pathlib import Path

import numpy as np
import yaml

from needlecue_runtime.vocab import AXES, CALIBRATION, angle_name
from pipeline.config import EffectScales, SimulateParams
from pipeline.logs import Log
from pipeline.rig.format import (
    BATCH_FILE,
    FORMAT,
    FSR_TIME,
    ID_PATTERN,
    TRIAL_COLUMNS,
    TRIALS_FILE,
    fsr_file,
    is_valid_id,
    ref_columns,
    ref_file,
)
from pipeline.sim import physics, rigs

MANIFEST = "simulate.json"
CHANNELS = ("fsr1", "fsr2", "fsr3")
TRAINING = "training"
PURPOSES = (TRAINING, CALIBRATION)  # batch.yaml `purpose` (rig.format.BatchMeta)

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class BatchPlan:
    """One simulated batch: which angles, how many tissue points each, its seed key (`number`,
    unique per batch), its tissue cast (`cast`: the cast's stiffness is seeded by it), the unit
    that records it, what it is for (batch.yaml `purpose`) and its role in the layout."""

    batch_id: str
    number: int
    angles_deg: tuple[float, ...]
    trials_per_angle: int
    cast: int
    unit_id: str
    purpose: str = TRAINING
    role: str = "training"  # training | held-out | new-unit | calibration (batch.yaml `simulator.role`)


def plan_batches(p: SimulateParams) -> list[BatchPlan]:
    """Training casts x training units, same-unit held-out casts, new-unit held-out casts, then
    the new units' calibration batches (see the module docstring); batches are numbered in that
    order, casts too. Batches with no trials are left out. ValueError if a unit id makes a batch
    id longer than the id pattern allows."""
    plans: list[BatchPlan] = []
    casts = itertools.count(p.train_batches + 1)  # the casts after the training casts

    def add(batch_id: str, angles: tuple[float, ...], trials: int, cast: int, unit: str, role: str) -> None:
        purpose = CALIBRATION if role == "calibration" else TRAINING
        plans.append(BatchPlan(batch_id, len(plans) + 1, angles, trials, cast, unit, purpose, role))

    for cast in range(1, p.train_batches + 1):
        for unit in p.units:
            add(f"sim-tissue-{cast}-{unit}", p.angles_deg, p.trials_per_angle, cast, unit, "training")
    for i, angle in enumerate(p.angles_deg):
        unit = p.units[i % len(p.units)]
        add(
            f"sim-heldout-{angle_name(angle)}deg",
            (angle,),
            p.heldout_trials_per_angle,
            next(casts),
            unit,
            "held-out",
        )
    for unit in p.new_units:
        for angle in p.angles_deg:
            name = f"sim-heldout-{angle_name(angle)}deg-{unit}"
            add(name, (angle,), p.heldout_trials_per_angle, next(casts), unit, "new-unit")
    for unit in p.new_units:
        add(
            f"sim-calib-{unit}",
            p.angles_deg,
            p.calibration_trials_per_angle,
            next(casts),
            unit,
            "calibration",
        )
    if bad := [b.batch_id for b in plans if not is_valid_id(b.batch_id)]:
        raise ValueError(f"batch ids {bad} do not match {ID_PATTERN.pattern}: choose shorter unit ids")
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


def draw_unit(p: SimulateParams, unit_id: str) -> physics.Estimator:
    """The estimator unit `unit_id` of the design `simulate.rig`: drawn from its id alone, the same
    in every batch it records."""
    return physics.draw_estimator(_rng(p, zlib.crc32(unit_id.encode())), p.effects, rigs.rig(p.rig))


def cast_scale(p: SimulateParams, cast: int) -> float:
    """Stiffness factor of one tissue cast: Ecoflex 00-30 casts differ from one to the next (E about
    97 kPa nominal). Seeded by the cast alone, so every unit that records a cast sees the same one."""
    return float(np.exp(p.effects.batch_variation * _rng(p, 1, cast).normal(0.0, 0.10)))


def unit_summary(est: physics.Estimator) -> dict[str, object]:
    """What makes a unit itself, rounded, for the manifest."""
    return {
        "gains": [round(g, 6) for g in est.gains],
        "preloads_n": [round(f, 6) for f in est.preloads_n],
        "azimuths_deg": [round(a, 4) for a in est.azimuths_deg],
        "drift_per_decade": round(est.drift_per_decade, 6),
    }


def simulate_batch(p: SimulateParams, plan: BatchPlan) -> Iterator[tuple[dict, physics.TrialRecord]]:
    """Yield (trial row, record) for every trial of one batch, in recording order."""
    est = draw_unit(p, plan.unit_id)
    scale = cast_scale(p, plan.cast)
    clocks = physics.Clocks(fsr_rate_hz=p.fsr_rate_hz, ref_rate_hz=p.ref_rate_hz)
    for a, angle in enumerate(plan.angles_deg):
        for k in range(1, plan.trials_per_angle + 1):
            rng = _rng(p, 2, plan.number, a, k)
            tissue = draw_tissue(rng, scale, p.effects)
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
    """batch.yaml of one simulated batch (unknown keys such as `simulator` are kept by ingest); the
    rig's read-out circuit as `sensor.front_end` when `simulate.declare_front_end`, and
    `reference.axes` when `simulate.reference_axes` is not all three."""
    design = rigs.rig(p.rig)
    sensor: dict[str, object] = {
        "unit_id": plan.unit_id,
        "channels": list(CHANNELS),
        "units": "counts" if p.effects.adc else "volts",
        "adc_bits": design.adc_bits,
        "vref_v": design.vref_v,
    }
    if p.declare_front_end:
        sensor["front_end"] = rigs.declared_front_end(design).model_dump(mode="json")
    reference: dict[str, object] = {"model": "ATI Nano17 (simulated)", "units": "N", "frame": "tissue"}
    if (axes := p.reference_axes) != AXES:  # the default, all three, is not written (rig-log/1's default)
        reference["axes"] = list(axes)
    return {
        "format": FORMAT,
        "batch_id": plan.batch_id,
        "purpose": plan.purpose,
        "recorded": (date(2026, 11, 2) + timedelta(days=plan.number)).isoformat(),
        "tissue": {"material": "Ecoflex 00-30", "notes": f"simulated cast {plan.cast} (needlecue simulate)"},
        "sensor": sensor,
        "reference": reference,
        "robot": {"insertion_speed_mm_s": 1.0, "insertion_time_s": 10.0, "retraction_speed_mm_s": 2.0},
        "simulator": {"seed": p.seed, "role": plan.role, "rig": p.rig},
    }


def write_batch(p: SimulateParams, plan: BatchPlan, out_dir: Path) -> int:
    """Write one batch folder; returns the number of estimator samples written."""
    folder = out_dir / plan.batch_id
    folder.mkdir(parents=True)
    rows, n_samples = [], 0
    integer = p.effects.adc
    axes = p.reference_axes
    columns = ref_columns(axes)
    for row, rec in simulate_batch(p, plan):
        rows.append(row)
        fsr = np.column_stack([rec.t_ms, rec.counts])
        fmt = ["%.3f"] + (["%d"] if integer else ["%.5f"]) * len(CHANNELS)
        _savetxt(folder / fsr_file(row["trial_id"]), fsr, fmt, (FSR_TIME, *CHANNELS))
        ref = np.column_stack([rec.t_s, rec.force[:, [AXES.index(a) for a in axes]]])
        _savetxt(folder / ref_file(row["trial_id"]), ref, ["%.5f"] * len(columns), columns)
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


def run(p: SimulateParams, out_dir: Path, *, log: Log = logger.info) -> list[str]:
    """Write all planned batches (or none when disabled) and the manifest; return batch ids."""
    rigs.rig(p.rig)  # an unknown rig fails before anything is cleared
    plans = plan_batches(p) if p.enabled else []  # a bad layout fails before anything is cleared
    prepare_out_dir(out_dir)
    written = []
    for plan in plans:
        n = write_batch(p, plan, out_dir)
        written.append(plan.batch_id)
        log(
            f"simulate: {plan.batch_id}: {len(plan.angles_deg) * plan.trials_per_angle} trials, "
            f"{n} estimator samples ({plan.role}, unit {plan.unit_id})"
        )
    units = {u: unit_summary(draw_unit(p, u)) for u in sorted({plan.unit_id for plan in plans})}
    manifest = {
        "generator": "needlecue simulate",
        # reference_axes only when not the default: the default's manifest is as it was before it
        "params": p.model_dump(mode="json", exclude={"reference_axes"} if p.reference_axes == AXES else None),
        "batches": written,
        "units": units,
    }
    (out_dir / MANIFEST).write_text(json.dumps(manifest, indent=2, sort_keys=True) + "\n")
    return written


def write_new_batch(
    p: SimulateParams,
    raw_dir: Path,
    batch_id: str,
    angles_deg: tuple[float, ...],
    trials_per_angle: int,
    unit_id: str | None = None,
    purpose: str = TRAINING,
) -> int:
    """One more simulated tissue cast, as a lab would drop it into `raw_dir`: a new batch folder
    (refused if it exists) recorded by `unit_id` (default: the first training unit; any id is a
    unit, drawn from that id), for `purpose` (training or calibration), its cast and tissue points
    seeded by its id. Returns the number of estimator samples written; ValueError on a bad id or
    purpose."""
    unit = p.units[0] if unit_id is None else unit_id
    for what, name in (("batch id", batch_id), ("unit id", unit)):
        if not is_valid_id(name):
            raise ValueError(f"{what} {name!r} does not match {ID_PATTERN.pattern}")
    if purpose not in PURPOSES:
        raise ValueError(f"purpose {purpose!r} is not one of {', '.join(PURPOSES)}")
    if (raw_dir / batch_id).exists():
        raise FileExistsError(f"{raw_dir / batch_id} exists: choose a new batch id")
    # numbers 1..1000 are plan_batches' own batches and casts; an id-derived number above them is
    # a new cast
    number = 1000 + zlib.crc32(batch_id.encode()) % 1_000_000
    role = "calibration" if purpose == CALIBRATION else "training"
    plan = BatchPlan(batch_id, number, tuple(angles_deg), trials_per_angle, number, unit, purpose, role)
    raw_dir.mkdir(parents=True, exist_ok=True)
    return write_batch(p, plan, raw_dir)
