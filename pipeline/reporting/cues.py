"""The angle cues in the report: the `## Angle cues` section, written from the cues stage's evaluation
(`pipeline.cues.document`) and packs (`needlecue_runtime.cues.pack`); its figures:
`pipeline.reporting.cue_figures`."""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from typing import Any

from needlecue_runtime.cues.pack import (
    CUES,
    DEVIATION_GROUPS,
    METHODS,
    REFERENCE,
    VERDICTS,
    AngleEstimator,
    CuePack,
    as_pack,
)
from needlecue_runtime.vocab import angle_name
from pipeline.cues.document import AngleMatrix, CueEvaluation, MethodResult, Results, ScoredCues, SkippedCues
from pipeline.reporting.cue_figures import method_label, scored_kinds


def _f(x: float | None, spec: str = ".1f") -> str:
    return "–" if x is None else format(x, spec)


def _pct(x: float | None, spec: str = ".1f") -> str:
    return "–" if x is None else f"{100 * x:{spec}} %"


def _confidence(pack: CuePack) -> str:
    """The P a cue needs, per way the estimator knows a unit, and how it was chosen."""
    chosen = pack.angle_estimator.confidence if pack.angle_estimator is not None else {}
    if not chosen:
        return f"{pack.params['min_confidence']}"
    how = {
        "training": "a training unit",
        "calibrated-1": "a new unit calibrated from 1 insertion per angle",
        "calibrated-2": "a new unit calibrated from 2 insertions per angle",
        "calibrated-3": "a new unit calibrated from 3 or more insertions per angle",
        "uncalibrated": "an uncalibrated one",
    }
    parts = [
        f"{c.min_confidence:g} for {how.get(reading, reading)} (cross-validated: a wrong cue in "
        f"{_pct(c.cv_wrong_frames, '.2f')} of insertion frames, a cue in {_pct(c.cv_coverage)}; "
        f"chosen: {c.chosen_by})"
        for reading, c in sorted(chosen.items(), key=lambda rc: rc[0] != "training")  # training first
    ]
    return "; ".join(parts)


def seen_table(res: Results, kinds: Sequence[str], within_s: float) -> list[str]:
    """What a trainee sees, side by side: the balanced accuracy within `within_s`, the wrong cues
    (at the insertion's end, at any time during it, per frame) and the coverage."""
    lines = [
        "What a trainee sees (a *wrong cue* is continue, correct or stop shown and not the truth; "
        "*coverage*: the share of insertion frames showing a cue at all; *balanced*: the mean over the "
        f"true cues of the share of trials whose cue is right, and stays right, within {within_s:g} s):",
        "",
        "| model | method | balanced within "
        f"{within_s:g} s | wrong at insertion end | wrong at any time | wrong frames | coverage |",
        "|---|---|---|---|---|---|---|",
    ]
    for _kind, method, label, r in _rows(res, kinds):
        seen = r.seen
        lines.append(
            f"| {label} | {method_label(method)} | {_pct(r.balanced_within_s)} | "
            f"{_pct(seen.wrong_final)} | {_pct(seen.wrong_ever)} | "
            f"{_pct(seen.wrong_frames)} | {_pct(seen.coverage_frames)} |"
        )
    return lines


def _rows(res: Results, kinds: Sequence[str]) -> list[tuple[str, str, str, MethodResult]]:
    """(kind, method, label, result) in report order, the reference-force bound last."""
    out = [(k, m, f"{k.upper()}", res[k][m]) for k in kinds for m in METHODS if m in res[k]]
    if REFERENCE in res and "paper" in res[REFERENCE]:
        out.append((REFERENCE, "paper", "measured force (bound)", res[REFERENCE]["paper"]))
    return out


def angle_cues(evaluation: CueEvaluation, packs: Mapping[float, CuePack | Mapping[str, Any]]) -> str:
    """The `## Angle cues` section of the report (image links relative to `reports/`). What the stage
    could not build or score is listed, with why, right under the description."""
    packs = {a: as_pack(p, f"the {angle_name(a)}° cue pack") for a, p in packs.items()}
    not_done = _not_done(evaluation, packs)
    if not isinstance(evaluation, ScoredCues) or not packs:
        return _render_built_only(packs, not_done)
    res, kinds = evaluation.results, scored_kinds(evaluation)
    ae = evaluation.angle_estimate_at_insertion_end
    some = next(iter(packs.values()))
    pp = some.params
    n_trials = sorted(set(evaluation.external_trials.values()))
    lines = [
        "## Angle cues",
        "",
        "The paper's conclusion as simulator cues: on the preset angle with the force in range, "
        "*continue*; about 15° off, *correct*; 30° or more off, *stop*. **Paper method**: the preset "
        "angle's model predicts the force; a running RMS distance between it and the preset angle's "
        "*standard profile* (mean reference force against time since contact over its training trials, "
        "in units of their spread) is cut by two thresholds, calibrated per model on the training splits "
        "of every angle. **Ours**: the estimator's own volts say at which angle it is held. At rest the "
        "needle's weight loads the tilted tripod differently at each angle; once the tissue pushes back, "
        "the direction in which the three FSRs' conductance moves from rest (through the unit's "
        "declared circuit; the volts where none is declared), taken each time its log-ratio to rest "
        "reaches one of the loading levels set by the training trials, differs too. "
        "Gaussian classes per evidence stage, "
        "fitted on the training splits of all angles and reading each estimator unit through its own "
        "class means and how sure they are (docs/units.md; "
        "temperature by leave-one-batch-out), give P(angle); the cue is the most probable "
        f"deviation class once its probability reaches {_confidence(some)}, with the profile's "
        f"force-in-range check (a predicted force above {pp['force_margin']:g}× the preset angle's largest "
        "training force means stop). Otherwise the trainee sees **no angle cue**, with why: an "
        "uncalibrated unit, not enough evidence yet, or evidence outside what training covered. Both "
        "methods are causal, frame by frame, and debounced "
        f"({pp['debounce_s']:g} s). Scored on the held-out batch: every preset angle against the "
        f"{'/'.join(str(n) for n in n_trials)} held-out trials of every angle; truth from |true − preset|: "
        "0° continue, 15° correct, ≥ 30° stop; the insertion spans the frames labelled `insertion` "
        "(from the reference force, for scoring only: the tracker never sees it).",
        "",
        *([*_NOT_DONE_HEAD, *not_done, ""] if not_done else []),
        *seen_table(res, kinds, float(pp["cue_within_s"])),
        "",
        "| model | method | right at insertion end | per frame during insertion | "
        "recall continue / correct / stop | force-check stops |",
        "|---|---|---|---|---|---|",
    ]
    for _kind, method, label, r in _rows(res, kinds):
        rec = " / ".join(_f(None if v is None else 100 * v, ".0f") for v in r.recall_final.values())
        alarms = "–" if r.force_alarm_trials is None else f"{r.force_alarm_trials} trials"
        lines.append(
            f"| {label} | {method_label(method)} | {_f(100 * (r.accuracy_final or 0))} % | "
            f"{_f(100 * (r.accuracy_frames or 0))} % | {rec} % | {alarms} |"
        )
    lines += [
        "",
        "Seconds into the insertion until the cue is right and stays right to its end (median / p90 "
        "over the trials that end right; 0 = right from the first insertion frame, e.g. from the rest "
        "reading), and how many trials end wrong:",
        "",
        "| model | method | " + " | ".join(f"{g}° off" for g in DEVIATION_GROUPS) + " |",
        "|---|---|" + "---|" * len(DEVIATION_GROUPS),
    ]
    for _kind, method, label, r in _rows(res, kinds):
        cells = []
        for g in DEVIATION_GROUPS:
            d = r.time_to_cue[g]
            cells.append(f"{_f(d.median_s)} / {_f(d.p90_s)} s; wrong {d.never_right}/{d.trials}")
        lines.append(f"| {label} | {method_label(method)} | " + " | ".join(cells) + " |")
    lines += ["", "Confusion at the end of the insertion (rows: true cue; columns: cue shown):", ""]
    header = "| model | method | true cue | " + " | ".join(CUES) + " |"
    lines += [header, "|---|---|---|" + "---|" * len(CUES)]
    for _kind, method, label, r in _rows(res, kinds):
        for name, row in zip(VERDICTS, r.confusion_final.counts, strict=True):
            lines.append(
                f"| {label} | {method_label(method)} | {name} | " + " | ".join(str(v) for v in row) + " |"
            )
    if ae is not None and some.angle_estimator is not None:
        lines += _angle_estimate_lines(ae, some.angle_estimator)
    lines += [
        "",
        *_findings(res, kinds),
        "",
        "![Confusion matrices of the cues at the end of the insertion](cues/confusion.png)",
        "",
        "![Share of trials with the right cue against seconds into the insertion](cues/time_to_cue.png)",
        "",
    ]
    return "\n".join(lines)


_NOT_DONE_HEAD = ["What this stage could not do, and why:", ""]


def _not_done(evaluation: CueEvaluation, packs: Mapping[float, CuePack]) -> list[str]:
    """Bullet lines: what is missing from the packs or the evaluation, and why (empty if nothing)."""
    out = []
    missing = {a: p.unavailable or {} for a, p in sorted(packs.items())}
    reasons = sorted({m["angle_estimator"] for m in missing.values() if "angle_estimator" in m})
    if reasons:
        out.append(
            f"- **No angle estimator** ({'; '.join(reasons)}): the packs have `angle_estimator: null` and "
            "the tracker's cue falls back to the paper's profile method, saying that the angle estimate "
            "is unavailable; only that method is scored."
        )
    whats: dict[tuple[str, str], list[float]] = {}
    for a, m in missing.items():
        for what, why in m.items():
            if what != "angle_estimator":
                whats.setdefault((what, why), []).append(a)
    for (what, why), angles in sorted(whats.items()):
        at = ", ".join(f"{angle_name(a)}°" for a in angles)
        if what == "standard_profile":
            out.append(f"- **No standard profile** at {at} ({why}): no paper-method cue there (it waits).")
        else:
            kind = what.rsplit(".", 1)[-1]
            out.append(f"- **No paper-method thresholds** for {kind} at {at}: {why}.")
    if isinstance(evaluation, SkippedCues):
        out.append(
            f"- **Cue evaluation skipped**: {evaluation.skipped}. `cues/evaluation.json` says so; "
            "its two figures only carry that message."
        )
    return out


def _render_built_only(packs: Mapping[float, CuePack], not_done: Sequence[str]) -> str:
    """The section when the cues could not be scored: what was built, what was not, and why."""
    built = []
    if packs:
        some = next(iter(packs.values()))
        per_angle = some.training.trials_per_angle
        with_profile = [a for a, p in sorted(packs.items()) if p.standard_profile is not None]
        if with_profile:
            built.append(
                f"the standard force profile of {', '.join(f'{angle_name(a)}°' for a in with_profile)}"
            )
        kinds = sorted({k for p in packs.values() for k in p.thresholds.profile})
        if kinds:
            built.append(f"paper-method thresholds ({', '.join(kinds)})")
        est = some.angle_estimator
        if est is not None:
            built.append(
                f"an angle estimator over {', '.join(f'{a:g}°' for a in est.classes_deg)} "
                f"({len(est.stages)} evidence stage(s))"
            )
        text = (
            "Simulator cues (continue / correct / stop from the preset angle's standard force profile and "
            "an angle estimate; see `pipeline/cues/`). Cue packs were built for the preset angle(s) "
            f"{', '.join(f'{angle_name(a)}°' for a in sorted(packs))} from the training splits (trials per "
            f"angle: {', '.join(f'{a}° {n}' for a, n in per_angle.items())}), with "
            + (", ".join(built) if built else "nothing usable")
            + "."
        )
    else:
        text = "No cue pack was built."
    return "\n".join(["## Angle cues", "", text, "", *_NOT_DONE_HEAD, *not_done, ""])


def _angle_estimate_lines(ae: AngleMatrix, estimator: AngleEstimator) -> list[str]:
    stages = estimator.stages
    est_cols = ae.cols_estimated_deg
    lines = [
        "",
        "Our angle estimate at the end of the insertion (rows: true angle; columns: estimate; the same "
        "for every model and preset angle):",
        "",
        "| true \\ estimated | " + " | ".join(f"{a:g}°" for a in est_cols) + " |",
        "|---|" + "---|" * len(est_cols),
    ]
    for a, row in zip(ae.rows_true_deg, ae.counts, strict=True):
        lines.append(f"| {a:g}° | " + " | ".join(str(v) for v in row) + " |")
    lines += [
        "",
        f"Exact in {_f(100 * (ae.exact or 0))} % of the held-out trials, within 15° in "
        f"{_f(100 * (ae.within_15 or 0))} %. Cross-validated accuracy on the training splits "
        f"({estimator.cv}) per evidence stage: "
        + ", ".join(
            f"{'rest' if i == 0 else f'level {i}'} "
            f"{_f(None if s.cv_accuracy is None else 100 * s.cv_accuracy, '.0f')} %"
            for i, s in enumerate(stages)
        )
        + ".",
    ]
    return lines


def _findings(res: Results, kinds: Sequence[str]) -> list[str]:
    """What the numbers say, computed, never written in advance."""
    out = []
    for kind in kinds:
        if "combined" not in res[kind]:
            continue
        ours, paper = res[kind]["combined"], res[kind]["paper"]
        a, b = ours.accuracy_final or 0, paper.accuracy_final or 0
        verdict = "helps" if a > b + 0.02 else ("does not help" if a < b - 0.02 else "changes little")
        line = (
            f"- {kind.upper()}: going past the paper {verdict}: {100 * a:.1f} % against {100 * b:.1f} % "
            "right at the end of the insertion."
        )
        weak = [c for c, v in paper.recall_final.items() if v is not None and v < 0.5]
        if weak:
            line += f" The profile comparison alone gets under half of the true *{'*, *'.join(weak)}* right."
        weak = [c for c, v in ours.recall_final.items() if v is not None and v < 0.8]
        if weak:
            line += f" Ours is weak on *{'*, *'.join(weak)}* (recall under 80 %)."
        if ours.force_alarm_trials:
            fin = ours.confusion_final.counts
            line += (
                f" Its force check fired in {ours.force_alarm_trials} trials "
                f"(true *continue* trials ending on *stop*: {fin[0][3]})."
            )
        out.append(line)
    ref = res.get(REFERENCE, {}).get("paper")
    if ref and kinds:
        best = max((res[k]["paper"].accuracy_final or 0) for k in kinds)
        r = ref.accuracy_final or 0
        if r > best + 0.1:
            out.append(
                f"- The profile comparison itself is not the weak link: on the measured force it is right "
                f"in {100 * r:.1f} % of the trials, against at most {100 * best:.1f} % on a model's "
                "prediction. A model trained at one angle maps another angle's volts onto its own angle's "
                "force direction (cutting and friction act along the needle, so they reach the tilted "
                "estimator the same way at every angle), so its predicted profile looks like the preset's "
                "even when the angle is off."
            )
        else:
            out.append(
                f"- On the measured force the profile comparison is right in {100 * r:.1f} % of the trials "
                f"(at most {100 * best:.1f} % on a model's prediction)."
            )
    models_agree = len({json.dumps(_final_counts(res[k].get("combined"))) for k in kinds}) == 1
    if len(kinds) > 1 and all("combined" in res[k] for k in kinds):
        out.append(
            "- Our cue reads the model's force only for the force-in-range check, so it "
            + (
                "gives the same result with every model."
                if models_agree
                else "differs between models only where that check fired."
            )
        )
    return out


def _final_counts(result: MethodResult | None) -> list[list[int]] | None:
    return None if result is None else result.confusion_final.counts
