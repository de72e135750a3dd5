"""The paper's published numbers (Tang et al., IEEE Sensors J. 2024) and its findings as checks:
the same code runs on the paper's numbers and on ours, so the report says where we agree."""

from __future__ import annotations

import itertools
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from needlecue_runtime.vocab import AXES, sorted_angles
from pipeline.metrics.document import AxisScore, Evaluation, ForceScores, MeanNrmse
from pipeline.metrics.scores import mean_over_axes
from pipeline.modelling.kinds import TABLE, kind_label

NETWORKS = ("fnn", "lstm")

# ---------------------------------------------------------------------------------------------
# The paper's numbers (for comparison only; extraction typos fixed as noted)
# ---------------------------------------------------------------------------------------------

# Table I, NRMSE % (Fx, Fy, Fz) on each angle's held-out "new dataset". The second "LS (45°)"
# row of the extracted table is the FNN row.
PAPER_TABLE1: dict[str, dict[str, tuple[float, float, float]]] = {
    "ls": {
        "0": (15.94, 14.14, 25.23),
        "15": (19.03, 20.17, 21.43),
        "30": (18.82, 21.50, 23.52),
        "45": (17.76, 18.75, 20.57),
        "60": (24.61, 25.53, 23.54),
        "75": (24.85, 31.72, 29.15),
    },
    "fnn": {
        "0": (9.92, 7.86, 7.35),
        "15": (10.56, 10.29, 9.74),
        "30": (4.84, 4.69, 4.48),
        "45": (7.18, 7.06, 7.18),
        "60": (8.29, 9.42, 9.25),
        "75": (7.62, 7.47, 7.20),
    },
}
# Averages as stated in the text of section V (they differ slightly from Table I's rows).
PAPER_MEAN_NRMSE = {"ls": (20.16, 21.96, 23.91), "fnn": (8.34, 8.11, 7.95)}
PAPER_MEAN_RMSE = {"ls": (0.0928, 0.2689, 0.4438), "fnn": (0.0383, 0.0098, 0.1476)}
# Table II (FNN); "1414%" in the extraction is 14.14 %.
PAPER_TABLE2 = {"fnn": {"15": (15.94, 14.14, 16.84), "30": (30.24, 40.06, 35.56)}}
# Table III; its "FNN (angle gap 30°)" row repeats Table II's 15° row, so it is the 15° gap.
PAPER_TABLE3 = {
    ("lstm", "30"): (6.11, 5.80, 5.74),
    ("fnn", "30"): (4.84, 4.69, 4.48),
    ("lstm", "gap15"): (14.38, 12.28, 14.14),
    ("fnn", "gap15"): (15.94, 14.14, 16.84),
}
# The kinds Table III compares, in its row order (LSTM, then FNN).
TABLE3_KINDS = tuple(dict.fromkeys(kind for kind, _ in PAPER_TABLE3))
# Within-angle NRMSE % by kind and angle: Table I, which has no LSTM rows, and the LSTM at 30° of Table III.
PAPER_WITHIN = {**PAPER_TABLE1, "lstm": {"30": PAPER_TABLE3[("lstm", "30")]}}
# Accuracies as stated in the abstract and conclusion.
PAPER_ACCURACY = {"ls": 78.02, "fnn_gap15": 84.36, "fnn_gap30_error": 35.28}


def _axes_dict(values: Sequence[float]) -> dict[str, float]:
    return dict(zip(AXES, (float(v) for v in values), strict=True))


def _scores(values: Sequence[float]) -> dict[str, AxisScore]:
    return {ax: AxisScore(rmse=None, nrmse_pct=v) for ax, v in _axes_dict(values).items()}  # NRMSE only


def paper_metrics() -> ForceScores:
    """The paper's numbers in our evaluation's shape, so the same checks run on both."""
    within = {m: {a: _scores(vals) for a, vals in rows.items()} for m, rows in PAPER_WITHIN.items()}
    mean = {}
    for m, vals in PAPER_MEAN_NRMSE.items():
        nrmse = _axes_dict(vals)
        overall = mean_over_axes(nrmse)
        mean[m] = MeanNrmse(within_angle=nrmse, accuracy_pct=None if overall is None else 100.0 - overall)
    angle_gap = {
        "fnn": {g: _axes_dict(v) for g, v in PAPER_TABLE2["fnn"].items()},
        "lstm": {"15": _axes_dict(PAPER_TABLE3[("lstm", "gap15")])},
    }
    return ForceScores.model_validate(
        {"within_angle": within, "mean": mean, "angle_gap": angle_gap, "gaps_deg": list(PAPER_TABLE2["fnn"])}
    )


# ---------------------------------------------------------------------------------------------
# Comparisons: the same computed checks on our numbers and on the paper's
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Check:
    """A claim evaluated on one set of numbers: holds (None: cannot be computed) and why."""

    holds: bool | None
    text: str


def _nrmse(metrics: ForceScores, model: str, angle: str, axis: str) -> float | None:
    score = metrics.within_angle.get(model, {}).get(angle, {}).get(axis)  # type: ignore[call-overload]
    return None if score is None else score.nrmse_pct


def _mean(metrics: ForceScores, model: str) -> MeanNrmse | None:
    return metrics.mean.get(model)


def _mean_nrmse(metrics: ForceScores, model: str) -> float | None:
    """The model's within-angle NRMSE averaged over its angles and axes (None: not known)."""
    mean = _mean(metrics, model)
    return mean_over_axes({} if mean is None else mean.within_angle)


def kinds_in(metrics: Evaluation) -> list[str]:
    """The model kinds evaluation.json has results for: the table's first, in its order (simplest
    first), then any other."""
    present = set(metrics.within_angle) | set(metrics.angle_gap_matrix)
    known = [m for m in TABLE if m in present]
    return known + sorted(present - set(known))


def accuracy_statement() -> str:
    """The paper's accuracies, as its section V, abstract and conclusion state them."""
    return (
        f"Paper: FNN above 90 % (section V averages: {100 - float(np.mean(PAPER_MEAN_NRMSE['fnn'])):.2f} %), "
        f"LS {PAPER_ACCURACY['ls']:.2f} %; FNN at the 15° gap {PAPER_ACCURACY['fnn_gap15']:.2f} %, "
        f"at the 30° gap an error of {PAPER_ACCURACY['fnn_gap30_error']:.2f} % "
        f"(accuracy {100 - PAPER_ACCURACY['fnn_gap30_error']:.2f} %)."
    )


def reference_angle(angles: Sequence[str], preferred: str = "30") -> str | None:
    """The paper's showcase angle (30°), or the first angle present."""
    if preferred in angles:
        return preferred
    return sorted_angles(angles)[0] if angles else None


def pct(x: float | None) -> str:
    return "—" if x is None else f"{x:.2f}%"


def check_ls_worse(metrics: ForceScores) -> Check:
    """LS has a higher NRMSE than every network on every axis, at every angle with both."""
    within = metrics.within_angle
    if "ls" not in within:
        return Check(None, "no LS results")
    compared, clean, exceptions = 0, 0, []
    for angle in sorted_angles(within["ls"]):
        nets = [n for n in NETWORKS if angle in within.get(n, {})]
        if not nets:
            continue
        compared += 1
        found = []
        for axis in (a for a in AXES if a in within["ls"][angle]):  # the axes its reference recorded
            ls = _nrmse(metrics, "ls", angle, axis)
            others = {n: _nrmse(metrics, n, angle, axis) for n in nets}
            # Unknown counts against the claim: "worse everywhere" must be shown, not assumed.
            beaten = [
                f"{kind_label(n)} {pct(v)}" for n, v in others.items() if ls is None or v is None or ls <= v
            ]
            if beaten:
                found.append(f"{angle}° F{axis[1]} (LS {pct(ls)} vs {', '.join(beaten)})")
        clean += not found
        exceptions += found
    if not compared:
        return Check(None, "no angle has both LS and a network")
    nets = [kind_label(n) for n in NETWORKS if n in within]
    named = (
        f"both networks ({', '.join(nets)}, each where it has results)" if len(nets) > 1 else f"the {nets[0]}"
    )
    text = f"LS is worse than {named} on every axis at {clean} of {compared} angles"
    text += f"; exceptions: {'; '.join(exceptions)}" if exceptions else ""
    return Check(clean == compared, text)


def _accuracy(metrics: ForceScores, model: str) -> float | None:
    mean = _mean(metrics, model)
    return None if mean is None else mean.accuracy_pct


def check_fnn_accuracy(metrics: ForceScores, threshold: float = 90.0) -> Check:
    """The FNN's average within-angle accuracy (100 − mean NRMSE) is above 90 %."""
    acc = _accuracy(metrics, "fnn")
    if acc is None:
        return Check(None, "no FNN results")
    return Check(
        acc > threshold,
        f"FNN average accuracy {acc:.2f}% ({'above' if acc > threshold else 'not above'} "
        f"{threshold:g}%), LS {pct(_accuracy(metrics, 'ls'))}",
    )


def check_ls_twice(metrics: ForceScores) -> Check:
    """LS's average NRMSE is at least twice the FNN's (the paper's "about two times")."""
    ls, fnn = (_mean_nrmse(metrics, m) for m in ("ls", "fnn"))
    if ls is None or fnn is None or fnn <= 0:
        return Check(None, "needs both LS and FNN averages")
    ratio = ls / fnn
    return Check(ratio >= 2.0, f"LS mean NRMSE {ls:.2f}% is {ratio:.2f}× the FNN's {fnn:.2f}%")


def check_gap_growth(metrics: ForceScores, model: str) -> Check:
    """Mean NRMSE grows strictly from the model's own angle (gap 0) through each summarised gap."""
    base = _mean_nrmse(metrics, model)
    gaps = metrics.angle_gap.get(model, {})
    steps = [("0", base)] + [(g, mean_over_axes(gaps[g])) for g in sorted(gaps, key=float)]
    if len(steps) < 2 or any(v is None for _, v in steps):
        return Check(None, f"{kind_label(model)}: not every gap has results")
    vals = [v for _, v in steps if v is not None]
    grows = all(b > a for a, b in itertools.pairwise(vals))
    path = " → ".join(f"{v:.2f}% ({g}°)" for g, v in steps if v is not None)
    return Check(grows, f"{kind_label(model)}: {path}: {'grows' if grows else 'does not grow'} with the gap")


def check_fnn_beats_lstm_at(metrics: ForceScores, angle: str) -> Check:
    """FNN has a lower mean NRMSE than the LSTM on the within-angle set of `angle`."""
    recorded = [a for a in AXES if any(a in metrics.within_angle.get(k, {}).get(angle, {}) for k in NETWORKS)]
    fnn = {a: _nrmse(metrics, "fnn", angle, a) for a in recorded}
    lstm = {a: _nrmse(metrics, "lstm", angle, a) for a in recorded}
    return _versus(fnn, lstm, f"at {angle}°")


def check_fnn_beats_lstm_gap(metrics: ForceScores, gap: str) -> Check:
    """FNN has a lower mean NRMSE than the LSTM over the pairs with angle gap `gap`."""
    gaps = metrics.angle_gap
    return _versus(gaps.get("fnn", {}).get(gap, {}), gaps.get("lstm", {}).get(gap, {}), f"at the {gap}° gap")


def _versus(fnn: Mapping[str, float | None], lstm: Mapping[str, float | None], where: str) -> Check:
    f, s = mean_over_axes(fnn), mean_over_axes(lstm)
    if f is None or s is None:
        return Check(None, f"needs FNN and LSTM results {where}")
    axes = [a for a in AXES if a in fnn and a in lstm]
    axes_won = sum(1 for a in axes if (fnn[a] or 0) < (lstm[a] or 0))
    return Check(
        f < s,
        f"{where}: FNN {f:.2f}% vs LSTM {s:.2f}% (mean over axes); "
        f"FNN lower on {axes_won} of {len(axes)} axes",
    )


def check_gap30_vs_ls(metrics: ForceScores, gap: str) -> Check:
    """With a large gap the FNN is no better than LS at its own angle, on X and Y (section V)."""
    fnn = metrics.angle_gap.get("fnn", {}).get(gap, {})
    ls_mean = _mean(metrics, "ls")
    ls = {} if ls_mean is None else ls_mean.within_angle
    if not fnn or not ls or any(fnn.get(a) is None or ls.get(a) is None for a in ("fx", "fy")):
        return Check(None, f"needs FNN at the {gap}° gap and LS averages, on fx and fy")
    worse = [a for a in AXES if fnn.get(a) is not None and ls.get(a) is not None and fnn[a] >= ls[a]]
    parts = ", ".join(f"F{a[1]} {fnn[a]:.2f}% vs {ls[a]:.2f}%" for a in AXES if fnn.get(a) is not None)
    holds = "fx" in worse and "fy" in worse
    return Check(
        holds,
        f"FNN at the {gap}° gap vs LS within-angle average: {parts}; "
        f"no better than LS on {', '.join('F' + a[1] for a in worse) or 'no axis'}",
    )


@dataclass(frozen=True)
class Finding:
    """One claim of the paper: the check on the paper's numbers, on ours, and the verdict."""

    claim: str
    paper: Check
    ours: Check

    @property
    def verdict(self) -> str:
        if self.paper.holds is None or self.ours.holds is None:
            return "cannot compare"
        return "agree" if self.paper.holds == self.ours.holds else "disagree"


def gap_key(metrics: ForceScores, wanted: float) -> str:
    """The summarised gap closest to `wanted` (the paper's 15° or 30°)."""
    gaps = metrics.gaps_deg or [f"{wanted:g}"]
    return min(gaps, key=lambda g: abs(float(g) - wanted))


def findings(metrics: Evaluation) -> list[Finding]:
    """Every computed comparison of our numbers with the paper's."""
    paper = paper_metrics()
    angles = list(metrics.datasets) or sorted_angles(a for m in metrics.within_angle.values() for a in m)
    ref = reference_angle(angles) or "30"
    small, large = gap_key(metrics, 15.0), gap_key(metrics, 30.0)
    out = [
        Finding(
            "LS is worse than the networks at every angle (Table I)",
            check_ls_worse(paper),
            check_ls_worse(metrics),
        ),
        Finding(
            "The FNN's accuracy is above 90 % (abstract)",
            check_fnn_accuracy(paper),
            check_fnn_accuracy(metrics),
        ),
        Finding(
            "LS's error is about twice the FNN's or more (section V)",
            check_ls_twice(paper),
            check_ls_twice(metrics),
        ),
    ]
    out += [
        Finding(
            "FNN error grows with the angle gap (Table II)",
            check_gap_growth(paper, "fnn"),
            check_gap_growth(metrics, "fnn"),
        ),
        Finding(
            f"FNN beats LSTM at {ref}° (Table III)",
            check_fnn_beats_lstm_at(paper, "30"),
            check_fnn_beats_lstm_at(metrics, ref),
        ),
        Finding(
            f"FNN beats LSTM at the {small}° gap (Table III)",
            check_fnn_beats_lstm_gap(paper, "15"),
            check_fnn_beats_lstm_gap(metrics, small),
        ),
        Finding(
            f"At the {large}° gap the FNN is no better than LS on X and Y (section V)",
            check_gap30_vs_ls(paper, "30"),
            check_gap30_vs_ls(metrics, large),
        ),
    ]
    return out


def gap_curve_statement(metrics: Evaluation) -> list[str]:
    """Per model: does the mean NRMSE rise with every step of the full gap curve (0° … max)?"""
    lines = []
    curves = metrics.gap_curve
    for model in [m for m in kinds_in(metrics) if m in curves]:
        curve = curves[model]
        steps = sorted(((float(g), v.mean) for g, v in curve.items()), key=lambda s: s[0])
        vals = [v for _, v in steps]
        if any(v is None for v in vals):
            lines.append(f"{kind_label(model)}: some gaps have no value")
            continue
        drops = [
            f"{a:g}°→{b:g}° ({va:.2f}% → {vb:.2f}%)"
            for (a, va), (b, vb) in itertools.pairwise(steps)
            if vb <= va
        ]
        path = ", ".join(f"{g:g}°: {v:.2f}%" for g, v in steps)
        verdict = "rises at every step" if not drops else f"does not rise at {'; '.join(drops)}"
        lines.append(f"{kind_label(model)} ({path}) {verdict}")
    return lines
