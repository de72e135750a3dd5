"""`report` stage: the last one; renders what the others computed into what people read.

Input: `DATA_DIR` (the truth of the plotted trials), `PRED_DIR` (the stored predictions),
`REPORTS_DIR/evaluation.json` (evaluate), `REPORTS_DIR/cues/{packs,evaluation.json}` (cues; without
them the report has no angle-cue section) and `REPORTS_DIR/needs/needs.json` (needs; without it, no
data-needs section) and `REPORTS_DIR/ledger/ledger.json` (ledger: the trials used with a flag).
Output in REPORTS_DIR: `report.md` (assembled from the section functions of
`pipeline.reporting.report` and `pipeline.reporting.cues`), `figures/` (Figs. 7-8 analogues, the
angle-gap heatmap), `plots/{gap,profile}.csv` (DVC plots) and `cues/{summary.md, confusion.png,
time_to_cue.png}`.

Usage: `python -m pipeline.execution.run report DATA_DIR PRED_DIR REPORTS_DIR [--params params.yaml]`.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import typer

from needlecue_runtime.cues.pack import read_pack
from needlecue_runtime.vocab import angle_name
from pipeline.config import EvaluateParams, TrainParams, load_section
from pipeline.cues.document import read_cue_evaluation
from pipeline.logs import setup
from pipeline.metrics.document import EVALUATION_FILE, read_evaluation
from pipeline.metrics.evaluation import gather, load_eval_sets
from pipeline.modelling.prediction_store import Predictions, read_inputs
from pipeline.needs.document import read_needs
from pipeline.reporting import cue_figures, cues, figures, report, unit_transfer
from pipeline.reporting.inputs import inputs_section
from pipeline.reporting.needs import how_much_data_you_need

_log = logging.getLogger("pipeline.stages").info  # not __name__: a stage runs as __main__


def main(data_dir: Path, pred_dir: Path, reports_dir: Path, params: Path = Path("params.yaml")) -> None:
    """Write report.md, its figures and DVC's plot data from metrics, predictions and cue results."""
    setup("report")
    train = load_section(TrainParams, "train", params)
    gaps = [float(g) for g in load_section(EvaluateParams, "evaluate", params).gaps_deg]
    angles, kinds = [angle_name(a) for a in train.angles], list(train.kinds)
    try:
        metrics = read_evaluation(reports_dir / EVALUATION_FILE)
        eval_sets = load_eval_sets(data_dir, angles, lambda _m: None)  # evaluate has warned already
        scored = gather(eval_sets, Predictions(pred_dir), kinds, angles, lambda _m: None)
    except (FileNotFoundError, ValueError) as e:
        _log(f"error: {e} (run the stages before report)")
        raise typer.Exit(1) from e
    cue_sections: list[str] = []
    cues_dir = reports_dir / "cues"
    evaluation = None
    if (cues_dir / "evaluation.json").is_file():
        evaluation = read_cue_evaluation(cues_dir / "evaluation.json")
        packs = {float(p.stem): read_pack(p) for p in (cues_dir / "packs").glob("*.json")}
        cue_figures.plot_confusion(evaluation, cues_dir / "confusion.png")
        cue_figures.plot_time_to_cue(evaluation, cues_dir / "time_to_cue.png")
        cue_sections.append(cues.angle_cues(evaluation, dict(sorted(packs.items()))))
        (cues_dir / "summary.md").write_text(cue_sections[0])
    else:
        _log(f"warning: no {cues_dir / 'evaluation.json'} (run the cues stage): no angle-cue section")

    plots = reports_dir / "plots"
    figures.write_csv(plots / "gap.csv", figures.gap_rows(metrics, kinds), ["gap_deg", *kinds])
    profile = figures.profile_rows(eval_sets, scored, kinds)
    figures.write_csv(plots / "profile.csv", profile, ["t_s", "reference", *kinds])
    fig_dir = reports_dir / "figures"
    figures.plot_profiles(eval_sets, scored, kinds, fig_dir / figures.FIGURES[0])
    figures.plot_gaps(eval_sets, scored, kinds, gaps, fig_dir / figures.FIGURES[1])
    figures.plot_gap_matrix(metrics, kinds, fig_dir / figures.FIGURES[2])
    unit_section = inputs_section(read_inputs(pred_dir)) + unit_transfer.estimator_units(metrics, evaluation)
    needs_file = reports_dir / "needs" / "needs.json"
    if needs_file.is_file():  # the needs stage drew its figure; the report links it
        unit_section += "\n\n" + how_much_data_you_need(read_needs(needs_file), "needs/needs.png")
    else:
        _log(f"warning: no {needs_file} (run the needs stage): no data-needs section")
    ledger_file = reports_dir / "ledger" / "ledger.json"
    flagged: list[dict] = []
    left_out: list[dict] = []
    if ledger_file.is_file():  # the trials used with a flag (a low alignment quality, kept)
        entries = json.loads(ledger_file.read_text())["entries"]
        flagged = [e for e in entries if e.get("flag")]
        left_out = [e for e in entries if e.get("unused_axes")]  # force axes their angle does not use
    else:
        _log(f"warning: no {ledger_file} (run the ledger stage): flagged trials not listed")
    text = report.render(
        metrics, [f"figures/{f}" for f in figures.FIGURES], cue_sections, unit_section, flagged, left_out
    )
    (reports_dir / "report.md").write_text(text)
    _log(f"report.md, {len(figures.FIGURES)} figures and the cue summary -> {reports_dir}")


if __name__ == "__main__":
    typer.run(main)
