"""`cues` stage: the cue pack of every preset angle, and how good the cues are on held-out trials.

Input: `DATA_DIR/<angle>/{train,external}.parquet`, the predict stage's `PRED_DIR` (every
model's forces on those frames) and the units' calibrations in `CAL_DIR` (which new units have one:
the cues are also scored per unit group, `by_unit_group`). Output in `OUT_DIR`:
`packs/<angle>.json` (shipped with each angle's registered model; see `pipeline.cues.packs`) and
`evaluation.json` (see
`pipeline.cues.score`); the report stage renders them. Small or unusual data never stops the
stage: what cannot be built or scored is left out and said, with why. It fails only on real
errors: missing input folders, bad params, inconsistent channels.

Usage: `python -m pipeline.execution.run cues DATA_DIR PRED_DIR CAL_DIR OUT_DIR [--params params.yaml]`.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import typer

from needlecue_runtime.cues.pack import write_pack
from needlecue_runtime.cues.units import cue_reading, departing_levels
from needlecue_runtime.unit_calibration import calibrated_units, read_units
from needlecue_runtime.vocab import angle_name
from pipeline.config import CuesParams, load_section
from pipeline.cues.document import write_cue_evaluation
from pipeline.cues.packs import build_packs
from pipeline.cues.score import cue_document, skipped_evaluation, track_external
from pipeline.cues.thresholds import Predicted
from pipeline.cues.unit_groups import evaluate_unit_groups
from pipeline.dataset.splits import SplitFiles, unit_roles
from pipeline.logs import setup
from pipeline.modelling.prediction_store import UNCALIBRATED, Predictions

_log = logging.getLogger("pipeline.stages").info  # not __name__: a stage runs as __main__


def main(
    data_dir: Path, pred_dir: Path, cal_dir: Path, out_dir: Path, params: Path = Path("params.yaml")
) -> None:
    """Build the cue packs (one per preset angle) and score the cues on the external trials."""
    setup("cues")
    started = time.perf_counter()
    try:
        if not params.is_file():
            raise FileNotFoundError(f"{params}: no such params file")
        p = load_section(CuesParams, "cues", params)
        predictions = Predictions(pred_dir)
        files = SplitFiles(data_dir)
        train = {a: f for a, f in files.by_angle("train").items() if len(f)}
        if not train:
            raise FileNotFoundError(f"{data_dir}: no <angle>/train.parquet with rows (run the split stage)")

        def predicted_for(preset: float) -> Predicted:
            """The preset's models of each kind on every angle's training frame."""
            kinds = [k for k in p.kinds if predictions.has(k, angle_name(preset))]
            for k in sorted(set(p.kinds) - set(kinds)):
                _log(f"warning: no {k} model at {angle_name(preset)}°: no {k} thresholds in its pack")
            return {k: predictions.on_split(k, angle_name(preset), "train", train) for k in kinds}

        circuits = files.front_ends()
        packs = build_packs(train, predicted_for, p, _log, circuits)
        available = tuple(k for k in p.kinds if all(predictions.has(k, angle_name(a)) for a in packs))
        for k in p.kinds:
            if k not in available:
                _log(f"warning: {k} lacks a model for some preset angle, not evaluated")
        if not available:
            evaluation = skipped_evaluation(
                f"no model kind of {list(p.kinds)} has a checkpoint (models/<kind>/<angle>/model.pt) "
                f"for every preset angle ({', '.join(angle_name(a) for a in packs)})",
                packs,
                p,
            )
        else:
            scored = p.model_copy(update={"kinds": available})
            docs = read_units(cal_dir)
            # what each calibrated unit's calibration insertions tell the angle estimator
            pack = next(iter(packs.values()), {})  # every preset's estimator has the same levels
            readings = {u: cue_reading(pack, d.cue_section()) for u, d in docs.items()}
            gathered = {u for u, d in docs.items() if d.cues is not None and d.cues.evidence}
            for u in sorted(u for u, (e, _) in readings.items() if e is None and u in gathered):
                _log(f"warning: {u}: its calibration's cue evidence is at other loading levels, not used")
            units = {u: e for u, (e, _) in readings.items() if e}
            maps = {u: m for u, (_, m) in readings.items() if m is not None}
            for u in sorted(maps):
                _log(
                    f"{u}: its calibration insertions depart from the training units' layout as they "
                    f"are and nowhere through its {docs[u].cues.mapped.kind} map on the "
                    "conductance: the cues read it through that map (docs/units.md)"
                )
            for u, e in sorted(units.items()):
                if away := departing_levels(pack, e):
                    _log(
                        f"warning: {u}: its calibration insertions sit unlike any shift of the training "
                        f"units' at evidence stage(s) {', '.join(map(str, away))} (0 is the rest reading): "
                        "no angle cue there, 'outside what training covered' (docs/units.md)"
                    )
            external = files.by_angle("external")
            tracked = track_external(
                external,
                scored,
                packs,
                lambda kind, preset, a: predictions.get(kind, angle_name(preset), angle_name(a), "external"),
                log=_log,
                units=units,
                circuits=circuits,
                maps=maps,
            )
            evaluation = cue_document(tracked, scored, packs)
            calibrated = calibrated_units(docs)
            _log("unit groups: the same unit and calibrated new units from these runs, uncalibrated replayed")
            evaluation["by_unit_group"] = evaluate_unit_groups(
                external,
                units,
                scored,
                packs,
                lambda kind, preset, a, split: predictions.get(
                    kind, angle_name(preset), angle_name(a), split
                ),
                UNCALIBRATED,
                unit_roles(data_dir),
                calibrated,
                circuits,
                tracked,
                maps,
            )
    except (FileNotFoundError, ValueError) as e:
        _log(f"error: {e}")
        raise typer.Exit(1) from e
    if evaluation.get("skipped"):
        _log(f"warning: cue evaluation skipped: {evaluation['skipped']}")

    (out_dir / "packs").mkdir(parents=True, exist_ok=True)
    for stale in (out_dir / "packs").glob("*.json"):  # a pack of an angle no longer trained
        stale.unlink()
    for preset, pack in packs.items():
        write_pack(out_dir / "packs" / f"{angle_name(preset)}.json", pack)
    write_cue_evaluation(out_dir / "evaluation.json", evaluation)
    _log(f"done in {time.perf_counter() - started:.1f} s -> {out_dir}")


if __name__ == "__main__":
    typer.run(main)
