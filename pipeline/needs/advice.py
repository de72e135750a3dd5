"""What to record next, in words: sentences computed from the needs curves (`pipeline.needs.curves`),
every number and every recommendation taken from them. Pure functions of the needs document's curves
(`pipeline.needs.document.Curves`)."""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import TypeVar

from pipeline.modelling.kinds import kind_label
from pipeline.needs.document import CueScores, CueUnscored, Curves, MeanScores, force_kind, networks

FLAT_REL = 0.05  # the force curve has flattened where all further data lowers its NRMSE by less than this
Point = tuple[int, float]  # (insertions per angle, figure)
S = TypeVar("S")  # a point of a curve: a ladder step, a calibration step


def force_label(name: str, names: Sequence[str]) -> str:
    """How the advice names the force curve `name` among the document's force curves `names`."""
    kind, stand_in = force_kind(name)
    if not stand_in:
        return kind_label(kind)
    fitted = [k for k, s in map(force_kind, names) if not s]
    return f"the networks' stand-in (a ridge regression, not the trained {networks(fitted)})"


def _pct(fraction: float) -> str:
    return f"{100 * fraction:.1f}"


def _plural(n: int, word: str) -> str:
    return f"{n} {word}" if n == 1 else f"{n} {word}s"


def reached(points: Sequence[Point], target: float) -> int | None:
    """The index of the first point from which every figure is at or above `target` (None: none)."""
    for i in range(len(points)):
        if all(v >= target - 1e-12 for _, v in points[i:]):
            return i
    return None


def flattens(points: Sequence[Point], rel: float = FLAT_REL) -> int | None:
    """The index of the first point after which more data lowers the figure (an error) by less than
    `rel` of it, the last point excluded (None: still falling there, or one point)."""
    for i in range(len(points) - 1):
        if all(v > (1 - rel) * points[i][1] for _, v in points[i + 1 :]):
            return i
    return None


def have_text(have: Mapping[str, int]) -> str:
    """The training insertions per angle the lab has: one number, or the range over the angles."""
    lo, hi = min(have.values()), max(have.values())
    return f"{lo}" if lo == hi else f"{lo} to {hi} (by angle)"


def cue_sentence(points: Sequence[Point], have: str, target_pct: float, within_s: float) -> str | None:
    """The cues against the training insertions per angle (figures as fractions)."""
    if not points:
        return None
    what = (
        f"{target_pct:g} % (balanced accuracy within {within_s:g} s, on the training units' held-out trials)"
    )
    target, last = target_pct / 100, points[-1]
    i = reached(points, target)
    if i is not None:
        n, v = points[i]
        at = (
            f"already at {n} insertions per angle, the fewest scored"
            if i == 0
            else f"at about {n} insertions per angle"
        )
        tail = (
            f"{_pct(v)} % there, {_pct(last[1])} % with {last[0]}" if i < len(points) - 1 else f"{_pct(v)} %"
        )
        return f"The cues reach {what} {at} ({tail}); you have {have}."
    if len(points) == 1:
        return (
            f"The cues do not reach {what} with the {have} you have: {_pct(last[1])} % (one step: no curve)."
        )
    first = points[0]
    rose = last[1] > first[1]
    moved = "rose" if rose else "fell" if last[1] < first[1] else "stayed"
    then = "record more insertions per angle" if rose else "more insertions per angle did not lift them here"
    return (
        f"The cues do not reach {what} with the {have} you have; from {first[0]} to {last[0]} insertions "
        f"per angle they {moved} from {_pct(first[1])} to {_pct(last[1])} %: {then}."
    )


def force_sentence(label: str, points: Sequence[Point], have: str) -> str | None:
    """One force model's mean NRMSE (%) against the training insertions per angle."""
    if not points:
        return None
    last = points[-1]
    if len(points) == 1:
        return (
            f"The force error of {label} is {last[1]:.2f} % mean NRMSE with {last[0]} insertions per angle "
            "(one step: no curve)."
        )
    i = flattens(points)
    if i is not None:
        n, v = points[i]
        return (
            f"The force error of {label} flattens at about {n} insertions per angle: {v:.2f} % mean NRMSE "
            f"there, {last[1]:.2f} % with {last[0]} (more insertions lower it by less than "
            f"{100 * FLAT_REL:g} %); you have {have}."
        )
    before = points[-2]
    lower = 100 * (1 - last[1] / before[1]) if before[1] else 0.0
    return (
        f"The force error of {label} is still falling at {last[0]} insertions per angle: from {before[0]} to "
        f"{last[0]} it went from {before[1]:.2f} to {last[1]:.2f} % mean NRMSE ({lower:.0f} % lower): "
        f"record more insertions per angle for a lower force error."
    )


def _listing(points: Sequence[Point]) -> str:
    return ", ".join(f"{k}: {_pct(v)} %" for k, v in points)


def left_out_sentence(
    points: Sequence[Point], units: int, target_pct: float, within_s: float, new_have: Mapping[str, int]
) -> str | None:
    """The cues of a training unit left out and calibrated from k of its own insertions per angle
    (mean over `units` units), and what that says for the new units' batches (`new_have`: their
    fewest calibration insertions per angle)."""
    if not points:
        return None
    who = f"a training unit read as a new one (each left out in turn, mean of {_plural(units, 'unit')})"
    what = f"{target_pct:g} % (balanced within {within_s:g} s)"
    i = reached(points, target_pct / 100)
    if i is None:
        first, last = points[0], points[-1]
        rose = len(points) > 1 and last[1] > first[1]
        then = (
            "record more calibration insertions per angle"
            if rose
            else "more calibration insertions did not lift it here"
        )
        return (
            f"Calibration: {who} does not reach {what} with up to {last[0]} calibration insertions per angle "
            f"({_listing(points)}): {then}."
        )
    k = points[i][0]
    at = f"{_plural(k, 'calibration insertion')} per angle"
    sentence = f"Calibration: {who} reaches {what} at {at} ({_listing(points)})"
    short = {u: n for u, n in new_have.items() if n < k}
    if short:
        units_have = ", ".join(f"{u} has {n}" for u, n in sorted(short.items()))
        return f"{sentence}; {units_have}: record {k} per angle for a new unit's calibration batch."
    if new_have:
        return f"{sentence}; the new units' calibration batches have that many."
    return f"{sentence}."


def new_unit_sentence(unit: str, points: Sequence[Point], fewest: int, asked: Sequence[int]) -> str | None:
    """A new unit's cues on its held-out trials, calibrated from its first k calibration insertions."""
    if not points:
        return None
    parts = ", ".join(f"{_pct(v)} % with {k}" for k, v in points)
    batch = f"{unit}'s own calibration batch ({fewest} per angle at the fewest)"
    sentence = f"{batch} gives {parts} per angle on its held-out trials"
    beyond = [k for k in asked if k > fewest]
    if beyond:
        return f"{sentence}; {', '.join(map(str, beyond))} per angle need a larger calibration batch."
    return f"{sentence}."


def _points(steps: Sequence[S], x: Callable[[S], int], get: Callable[[S], float | None]) -> list[Point]:
    """(x, figure) of the steps that have the figure."""
    return [(int(x(s)), float(v)) for s in steps if (v := get(s)) is not None]


def _balanced(figures: object) -> float | None:
    """The balanced accuracy of scored cue figures (None: not scored)."""
    return figures.balanced_within_s if isinstance(figures, CueScores | MeanScores) else None


def sentences(needs: Curves) -> list[str]:
    """The advice of a needs document, in the order: cues, force, calibration."""
    p, training = needs.params, needs.training
    target, within = float(p.cue_target_pct), float(needs.cue_within_s)
    have = have_text(training.have_per_angle)
    steps = training.steps
    out = [
        cue_sentence(_points(steps, lambda s: s.per_angle, lambda s: _balanced(s.cues)), have, target, within)
    ]
    unscored = [(s.per_angle, s.cues.unavailable) for s in steps if isinstance(s.cues, CueUnscored)]
    if unscored:
        counts = ", ".join(str(n) for n, _ in unscored)
        out.append(f"With {counts} insertions per angle the cues could not be scored: {unscored[0][1]}.")
    names = [m.name for m in training.force_models]
    for name in names:
        figure = _points(
            steps,
            lambda s: s.per_angle,
            lambda s, n=name: f.mean_nrmse_pct if (f := s.force.get(n)) is not None else None,
        )
        out.append(force_sentence(force_label(name, names), figure, have))

    calibration = needs.calibration
    new = calibration.new_units
    fewest = {u: min(e.calibration_insertions.values()) for u, e in new.items()}
    new_lines = [
        new_unit_sentence(
            u,
            _points(e.steps, lambda s: s.k, _balanced),
            fewest[u],
            list(p.calibration_insertions),
        )
        for u, e in sorted(new.items())
    ]
    loo = calibration.leave_one_unit_out
    if loo is None:
        units = training.units
        one = f"one training unit ({units[0]})" if len(units) == 1 else "fewer than two training units"
        shown = [s for s in new_lines if s]
        tail = "; ".join(shown) if shown else "no new unit's calibration batch shows the curve either"
        out.append(f"Leave-one-unit-out is not possible with {one}: {tail.rstrip('.')}.")
    else:
        mean = loo.mean
        units = max((m.units for m in mean), default=0)
        out.append(left_out_sentence(_points(mean, lambda m: m.k, _balanced), units, target, within, fewest))
        out += new_lines
    return [s for s in out if s]
