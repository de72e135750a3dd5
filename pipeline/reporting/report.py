"""report.md, assembled from small section functions: each heading is written by the function of
the same name (`datasets` writes "## Datasets", `table1` "## Table I ...", and so on), and
`render` puts them in order. Inputs are data only: the evaluation (`pipeline.metrics.document`), the
cue evaluation, the packs."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from needlecue_runtime.vocab import AXES, axes_of, sorted_angles
from pipeline.metrics.document import AxisNrmse, Evaluation, Scores
from pipeline.metrics.paper import (
    PAPER_MEAN_NRMSE,
    PAPER_MEAN_RMSE,
    PAPER_TABLE1,
    PAPER_TABLE2,
    PAPER_TABLE3,
    PAPER_WITHIN,
    TABLE3_KINDS,
    accuracy_statement,
    check_gap_growth,
    findings,
    gap_curve_statement,
    gap_key,
    kinds_in,
    pct,
    reference_angle,
)
from pipeline.metrics.scores import mean_over_axes
from pipeline.modelling.kinds import kind_label
from pipeline.reporting.style import fmt, table

FLAGGED_SHOWN = 5  # flagged trials named in report.md; the ledger lists them all

SIMULATOR_NOTE = """\
The data come from the project's pipeline, normally fed by its built-in rig simulator
(`pipeline/sim/physics.py`, see `docs/physics.md`): Okamura's needle–tissue force model, a
tripod estimator tilted with the insertion angle, FSRs with threshold, hysteresis, drift and
part-to-part spread behind a viscoelastic silicone layer, a 10-bit ADC and two
unsynchronised clocks. It is faithful in kind but it is not the authors' rig: tissue casts,
FSR parts, preload, connector geometry, noise levels and trial protocol are estimates from
published figures, not measurements of their device, and nothing was tuned to reproduce
their numbers. Absolute NRMSE values therefore differ; what physics should carry over is the
order (LS clearly worse than the networks, error growing with the angle gap). Other known
differences: the paper does not document its splits (we split by trial and hold out a whole
batch per angle as the "new dataset"); it does not describe its LSTM (ours sees only the
estimator's own history in a fixed window); NRMSE divides by the reference range of the set
scored, so a set with a smaller range reads worse at the same RMSE; and the paper's gap rows
come from single (model, dataset) pairs, while ours average every pair with that gap, in
both directions."""


def recorded(metrics: Evaluation) -> tuple[str, ...]:
    """The force axes the evaluation scored (those the references recorded): the report's columns."""
    scored = {a for by_angle in metrics.within_angle.values() for s in by_angle.values() for a in s}
    return axes_of(scored) or AXES


def _axis_cells(values: Mapping[str, float | None] | None, axes: Sequence[str]) -> list[str]:
    return [pct((values or {}).get(a)) for a in axes]


def _paper_cells(values: Sequence[float] | None, axes: Sequence[str]) -> list[str]:
    """The paper's figures (fx, fy, fz) on `axes`."""
    return [pct(values[AXES.index(a)]) for a in axes] if values else ["—"] * len(axes)


def _headers(axes: Sequence[str], paper: bool = True) -> list[str]:
    """ "Fx", "Fy", "Fz" (then "paper Fx", ...) for the axes shown."""
    ours = [f"F{a[1]}" for a in axes]
    return ours + [f"paper {h}" for h in ours] if paper else ours


def _within_nrmse(table: Mapping[str, Mapping[str, Scores]], model: str, angle: str) -> AxisNrmse | None:
    """NRMSE per axis of one (model, angle) of `within_angle` or `within_angle_test`."""
    scores = table.get(model, {}).get(angle)
    return None if scores is None else {a: v.nrmse_pct for a, v in scores.items()}


def title(metrics: Evaluation) -> list[str]:
    """# Evaluation: the title and how the numbers are defined."""
    out = ["# Evaluation: needle force estimators against the paper (Tang et al., IEEE Sensors J. 2024)", ""]
    out += [
        "NRMSE = 100 · RMSE / (max(ref) − min(ref)) per axis over every sample of the set scored "
        "(eq. (3)-(4)); accuracy = 100 − NRMSE. All numbers are computed by `pipeline/metrics/` "
        "and also in `evaluation.json` (the headline figures in `metrics.json`); paper values are "
        "copied from the text as extracted "
        '(typos fixed: the second "LS (45°)" row of Table I is the FNN row; "1414%" is 14.14 %; '
        'Table III\'s "FNN (angle gap 30°)" row is the 15° gap row). Models see only their inputs: '
        "the force columns are dropped before `predict`.",
        "",
    ]
    return out


def datasets(
    metrics: Evaluation, flagged: Sequence[Mapping[str, Any]] = (), left_out: Sequence[Mapping[str, Any]] = ()
) -> list[str]:
    """## Datasets: which set each angle is scored on, the force axes scored, the trials used with a
    flag, and the batches whose recorded axes an angle leaves out (ledger entries)."""
    datasets = metrics.datasets
    out = [
        "## Datasets",
        "",
        "Table I and the angle-gap tables score each model on an angle's **external** set: the "
        'held-out batch, never seen in training, standing for the paper\'s "new dataset" '
        "(an angle without external rows falls back to its test split, marked below). The "
        "test-split table uses the trials of the training batches that the split stage kept out "
        "of training and validation.",
        "",
    ]
    out += table(
        ["angle", "scored set", "trials", "rows", "test rows", "batches"],
        (
            [
                f"{a}°",
                d.source,
                str(d.n_trials),
                str(d.n_rows),
                str(d.n_test_rows),
                ", ".join(d.batches),
            ]
            for a, d in ((a, datasets[a]) for a in sorted_angles(datasets))
        ),
    )
    without = [a for a in sorted_angles(datasets) if datasets[a].source != "external"]
    if without:
        out += [
            "",
            f"**No external set at {', '.join(f'{a}°' for a in without)}.** No usable trial of a held-out "
            "batch (`split.external_batches`) reached "
            + ("this angle" if len(without) == 1 else "these angles")
            + ": every figure below for "
            + ("it" if len(without) == 1 else "them")
            + " is on the test split, trials of the training batches' casts, and says nothing about "
            "data never seen in training. `reports/ledger` says where each trial went.",
        ]
    if recorded(metrics) != AXES:
        axes = ", ".join(recorded(metrics))
        out += [
            "",
            f"**Force axes: {axes}.** The references recorded these (batch.yaml `reference.axes`): "
            "the models estimate them alone, and every table and figure shows them alone.",
        ]
    if left_out:
        where: dict[tuple[str, str], tuple[str, set[str]]] = {}
        for e in left_out:
            key = (str(e.get("angle")), str(e["batch_id"]))
            where.setdefault(key, (", ".join(e["unused_axes"]), set()))[1].add(str(e.get("use")))
        parts = [
            f"{angle}°: `{batch}`'s {axes} ({', '.join(sorted(uses))})"
            for (angle, batch), (axes, uses) in sorted(
                where.items(), key=lambda kv: (float(kv[0][0]), kv[0][1])
            )
        ]
        out += [
            "",
            "**Force axes left out.** Not every batch of these angles records them, so the angle's models "
            "are trained and scored on the axes all its batches record (docs/rig-log-format.md): "
            + "; ".join(parts)
            + ". `reports/ledger/ledger.md` lists the trials.",
        ]
    if flagged:
        shown = [f"`{e['batch_id']}/{e['trial_id']}` ({e['flag']})" for e in flagged[:FLAGGED_SHOWN]]
        more = f", and {len(flagged) - FLAGGED_SHOWN} more" if len(flagged) > FLAGGED_SHOWN else ""
        out += [
            "",
            f"**{len(flagged)} trial(s) used with a flag**, kept because nothing shows their files "
            "disagree; the validation figures include them: " + "; ".join(shown) + more + ". "
            "`reports/ledger/ledger.md` lists them all.",
        ]
    return out


def table1(metrics: Evaluation, kinds: list[str], angles: list[str]) -> list[str]:
    """## Table I: within-angle NRMSE on the external set, with the average RMSE."""
    axes = recorded(metrics)
    out: list[str] = []
    out += ["", "## Table I: within-angle NRMSE on the external set", ""]
    rows = []
    for angle in angles:
        for m in kinds:
            ours = _within_nrmse(metrics.within_angle, m, angle)
            paper = PAPER_WITHIN.get(m, {}).get(angle)
            if ours is None and paper is None:
                continue
            rows.append([f"{kind_label(m)} ({angle}°)", *_axis_cells(ours, axes), *_paper_cells(paper, axes)])
    for m in kinds:
        mean = metrics.mean.get(m)
        n = 0 if mean is None else mean.n_angles
        rows.append(
            [
                f"**{kind_label(m)} average** ({n} angles)",
                *_axis_cells(None if mean is None else mean.within_angle, axes),
                *_paper_cells(PAPER_MEAN_NRMSE.get(m), axes),
            ]
        )
    out += table(["method", *_headers(axes)], rows)
    out += [
        "",
        "The paper's Table I has no LSTM rows; its LSTM at 30° is from Table III. Paper averages are "
        "those stated in section V (Table I's own rows average to "
        + ", ".join(
            f"{kind_label(m)} "
            + "/".join(f"{v:.2f}" for v in np.mean(list(PAPER_TABLE1[m].values()), axis=0))
            for m in PAPER_TABLE1
        )
        + " %).",
        "",
        "Average RMSE over angles (N):",
        "",
    ]
    rmse_rows = []
    for m in kinds:
        mean = metrics.mean.get(m)
        r = {} if mean is None else mean.within_angle_rmse
        paper_r = PAPER_MEAN_RMSE.get(m)
        rmse_rows.append(
            [
                kind_label(m),
                *(fmt(r.get(a)) or "—" for a in axes),
                *([f"{paper_r[AXES.index(a)]:.4f}" for a in axes] if paper_r else ["—"] * len(axes)),
            ]
        )
    out += table(["method", *_headers(axes)], rmse_rows)
    return out


def test_split(metrics: Evaluation, kinds: list[str], angles: list[str]) -> list[str]:
    """### Within-angle NRMSE on the test split."""
    axes = recorded(metrics)
    out: list[str] = []
    out += ["", "### Within-angle NRMSE on the test split (ours only)", ""]
    rows = [
        [f"{kind_label(m)} ({a}°)", *_axis_cells(_within_nrmse(metrics.within_angle_test, m, a), axes)]
        for a in angles
        for m in kinds
        if _within_nrmse(metrics.within_angle_test, m, a) is not None
    ]
    out += table(["method", *_headers(axes, paper=False)], rows) if rows else ["No test-split results."]
    return out


def table2(metrics: Evaluation, kinds: list[str]) -> list[str]:
    """## Table II: angle gaps, and the train-by-data angle matrix per model."""
    axes = recorded(metrics)
    out: list[str] = []
    out += [
        "",
        "## Table II: angle gaps (mean NRMSE over every pair of train and data angle with that gap)",
        "",
    ]
    rows = []
    pairs = metrics.angle_gap_pairs
    for g in metrics.gaps_deg:
        for m in kinds:
            ours = metrics.angle_gap.get(m, {}).get(g)
            if ours is None:
                continue
            rows.append(
                [
                    f"{kind_label(m)} ({g}° gap)",
                    str(pairs.get(m, {}).get(g, 0)),
                    *_axis_cells(ours, axes),
                    *_paper_cells(PAPER_TABLE2.get(m, {}).get(g), axes),
                ]
            )
    out += table(["model", "pairs", *_headers(axes)], rows)
    out += ["", "Mean NRMSE over axes, train angle (rows) against data angle (columns):", ""]
    for m in kinds:
        mat = metrics.angle_gap_matrix.get(m)
        if not mat:
            continue
        cols = sorted_angles(d for row in mat.values() for d in row)
        out += [f"**{kind_label(m)}**", ""]
        out += table(
            ["train \\ data", *(f"{d}°" for d in cols)],
            (
                [f"{t}°", *(fmt(mean_over_axes(mat[t].get(d, {})), ".2f") or "—" for d in cols)]
                for t in sorted_angles(mat)
            ),
        )
        out.append("")
    return out


def table3(metrics: Evaluation, angles: list[str]) -> list[str]:
    """## Table III: FNN against LSTM, the kinds the paper's Table III compares (`TABLE3_KINDS`), at
    the reference angle, then at the small gap."""
    axes = recorded(metrics)
    ref = reference_angle(angles) or "30"
    small = gap_key(metrics, 15.0)
    rows = [
        [
            f"{kind_label(m)} ({ref}°)",
            *_axis_cells(_within_nrmse(metrics.within_angle, m, ref), axes),
            *_paper_cells(PAPER_TABLE3.get((m, "30")), axes),
        ]
        for m in TABLE3_KINDS
    ]
    rows += [
        [
            f"{kind_label(m)} (angle gap {small}°)",
            *_axis_cells(metrics.angle_gap.get(m, {}).get(small), axes),
            *_paper_cells(PAPER_TABLE3.get((m, "gap15")), axes),
        ]
        for m in TABLE3_KINDS
    ]
    heading = [f"## Table III: FNN against LSTM ({ref}°, and the {small}° gap)", ""]
    return heading + table(["method & dataset", *_headers(axes)], rows)


def accuracy(metrics: Evaluation, kinds: list[str]) -> list[str]:
    """## Accuracy: 100 − mean NRMSE, own angle and per gap."""
    out: list[str] = []
    out += ["", "## Accuracy (100 − mean NRMSE over axes)", ""]
    rows = []
    for m in kinds:
        mean = metrics.mean.get(m)
        gap_acc = {} if mean is None else mean.angle_gap_accuracy_pct
        rows.append(
            [
                kind_label(m),
                pct(None if mean is None else mean.accuracy_pct),
                *(pct(gap_acc.get(g)) for g in metrics.gaps_deg),
            ]
        )
    out += table(["model", "own angle", *(f"{g}° gap" for g in metrics.gaps_deg)], rows)
    out += ["", accuracy_statement()]
    return out


def figures_section(figures: Sequence[str]) -> list[str]:
    """## Figures, with captions."""
    out: list[str] = []
    if figures:
        out += ["", "## Figures", ""]
        captions = {
            "fig7_profiles.png": "Fig. 7 analogue: reference against each angle's own models on one "
            "external trial per angle (the first by id, not a chosen one).",
            "fig8_gaps.png": "Fig. 8 analogue: one angle's models on trials of angles 15° and 30° away.",
            "gap_matrix.png": "Mean NRMSE over axes for every model on every angle's external set.",
        }
        for f in figures:
            name = Path(f).name
            out += [f"![{name}]({f})", "", captions.get(name, ""), ""]
    return out


def agreement(metrics: Evaluation, kinds: list[str]) -> list[str]:
    """## Where we agree with the paper and where we do not; why a simulator differs."""
    out: list[str] = []
    out += ["", "## Where we agree with the paper and where we do not", ""]
    out += ["Each claim is checked by the same code on the paper's numbers and on ours.", ""]
    for fd in findings(metrics):
        out += [
            f"- **{fd.claim}: {fd.verdict}.**",
            f"  Paper: {fd.paper.text}.",
            f"  Ours: {fd.ours.text}.",
        ]
    growth = [check_gap_growth(metrics, m) for m in kinds if m in metrics.angle_gap]
    if growth:
        gaps = ", ".join(f"{g}°" for g in metrics.gaps_deg)
        out += ["", f"Error grows with the angle gap for each model (own angle, then {gaps}):", ""]
        out += [f"- {'yes' if c.holds else 'no'}: {c.text}." for c in growth]
    curve = gap_curve_statement(metrics)
    if curve:
        out += ["", "Over every gap present (mean NRMSE over axes and pairs):", ""]
        out += [f"- {line}." for line in curve]
    out += ["", "### Why a simulator's numbers differ from the rig's", "", SIMULATOR_NOTE, ""]
    return out


def render(
    metrics: Evaluation,
    figures: Sequence[str] = (),
    cue_sections: Sequence[str] = (),
    unit_section: str = "",
    flagged: Sequence[Mapping[str, Any]] = (),
    left_out: Sequence[Mapping[str, Any]] = (),
) -> str:
    """report.md: the sections in order; `cue_sections` (the angle cues' Markdown), then
    `unit_section` (the estimator units') come last; `flagged`: the ledger's entries used with a
    flag; `left_out`: those whose reference records force axes their angle's models do not use."""
    kinds = kinds_in(metrics)
    angles = sorted_angles(list(metrics.datasets) + [a for m in metrics.within_angle.values() for a in m])
    out = title(metrics) + datasets(metrics, flagged, left_out)
    out += table1(metrics, kinds, angles) + test_split(metrics, kinds, angles)
    out += table2(metrics, kinds) + table3(metrics, angles) + accuracy(metrics, kinds)
    out += figures_section(figures) + agreement(metrics, kinds)
    report = "\n".join(out)
    for section in [*cue_sections, unit_section]:
        if section.strip():
            report = report.rstrip("\n") + "\n\n" + section.strip("\n") + "\n"
    return report
