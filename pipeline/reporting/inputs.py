"""The report's "What the models read" section: each model's inputs, the circuit they are read
through, and how they were chosen (pinned in params, or by validation with each candidate's score).
Data in: the predict stage's `inputs.json` (from the checkpoints)."""

from __future__ import annotations

from collections.abc import Mapping

from needlecue_runtime.features import INPUT_KINDS, ModelInputs
from needlecue_runtime.frontend import Divider
from needlecue_runtime.vocab import sorted_angles
from pipeline.modelling.choice import Choice, pool
from pipeline.modelling.kinds import kind_label
from pipeline.modelling.prediction_store import ModelReads
from pipeline.reporting.style import table


def _circuit(inputs: ModelInputs) -> str:
    fe = inputs.front_end
    if fe is None:
        return "–"
    if isinstance(fe, Divider):
        return f"divider {fe.supply_v:g} V, {fe.fixed_kohm:g} kΩ, FSR at {fe.fsr_at}"
    return f"transimpedance {fe.drive_v:g} V, {fe.feedback_kohm:g} kΩ"


def inputs_section(models: Mapping[str, Mapping[str, ModelReads]]) -> str:
    """The section's Markdown ("" when the predict stage recorded no model)."""
    if not models:
        return ""
    scored = {k for m in models.values() for r in m.values() if r.choice is not None for k in r.choice.scores}
    kinds_seen = [k for k in INPUT_KINDS if k in scored]  # the kinds' own order: simplest first
    rows = []
    folds = set()

    def cells(scores: Mapping[str, float | None]) -> list[str]:
        return [
            "–" if k not in scores else ("n/a" if scores[k] is None else f"{scores[k]:.2f}")
            for k in kinds_seen
        ]

    for kind in models:
        scored: dict[str, Choice] = {}  # each angle's own scores: their mean chose one kind for all
        for angle in sorted_angles(models[kind]):
            r = models[kind][angle]
            choice = r.choice
            if choice is not None:
                only = f"; candidates: {choice.only}" if choice.only else ""
                folds.add(f"{choice.folds}; stand-in: {choice.stand_in}{only}")
                scored[angle] = choice
            how = "validation" if choice is not None else "params"
            rows.append([kind_label(kind), f"{angle}°", f"**{r.inputs.kind}**", how, _circuit(r.inputs)])
            rows[-1] += cells({} if choice is None else choice.scores)
        read = {c.chosen for c in scored.values()}
        if len(scored) > 1 and len(read) == 1:  # one kind for all angles: the mean that chose it
            mean = pool(scored).scores
            rows.append([kind_label(kind), "mean", f"**{read.pop()}**", "all angles", "–", *cells(mean)])
    header = ["model", "angle", "inputs", "chosen by", "read through", *(f"{k} (%)" for k in kinds_seen)]
    lines = [
        "## What the models read",
        "",
        "Each model's inputs (docs/units.md): pinned in params.yaml, or chosen by validation on this "
        "data (`inputs.kind: auto`, pipeline/modelling/choice.py), with each candidate's mean NRMSE on "
        "the held-out folds; one kind per model for all its angles, by the mean over the angles (row "
        '"mean"). The conductance kinds are candidates only where the training units declare '
        "their circuit (batch.yaml `sensor.front_end`), and the only ones where a unit the model "
        "serves declares another.",
        "",
        *(f"- Folds: {f}" for f in sorted(folds)),
        "",
        *table(header, rows),
        "",
    ]
    return "\n".join(lines)
