"""Collecting what is wrong with one batch while it is read: its `Problem`s, without repeats and
without flooding the report, and its warnings, grouped by kind.
"""

from __future__ import annotations

from collections import Counter, defaultdict
from collections.abc import Iterable, Sequence
from pathlib import Path

from pipeline.rig.format import Problem

# Per file and column, report this many problems one by one, then one "... and N more" line.
MAX_PER_COLUMN = 5


class ProblemLog:
    """The Problems of one batch, in discovery order.

    A cell already blamed (same file, line, column) is not blamed again, so GX does not
    repeat what the parser said more precisely. Per file and column at most MAX_PER_COLUMN
    are listed; the rest are counted into one summary Problem (a column of text would
    otherwise flood the report), but every affected trial is still set aside.
    """

    def __init__(self, batch_id: str) -> None:
        self.batch_id = batch_id
        self.items: list[Problem] = []
        self.bad_trials: set[str] = set()
        self.bad_lines: defaultdict[str, set[int]] = defaultdict(set)
        self._cells: set[tuple[str, int, str | None]] = set()
        self._counts: Counter[tuple[str, str | None]] = Counter()
        self._trial_of: dict[tuple[str, str | None], str | None] = {}

    def add(
        self,
        file: str,
        reason: str,
        *,
        trial_id: str | None = None,
        line: int | None = None,
        column: str | None = None,
    ) -> None:
        """Record one Problem (and mark its trial and line bad)."""
        if trial_id is not None:
            self.bad_trials.add(trial_id)
        if line is not None:
            if (file, line, column) in self._cells:
                return
            self._cells.add((file, line, column))
            self.bad_lines[file].add(line)
        key = (file, column)
        self._counts[key] += 1
        self._trial_of[key] = trial_id
        if self._counts[key] <= MAX_PER_COLUMN:
            self.items.append(Problem(self.batch_id, file, reason, trial_id, line, column))

    def extend(self, problems: Iterable[Problem]) -> None:
        for p in problems:
            self.add(p.file, p.reason, trial_id=p.trial_id, line=p.line, column=p.column)

    def finish(self) -> list[Problem]:
        """The listed Problems plus one summary Problem per capped file and column."""
        out = list(self.items)
        for (file, column), n in self._counts.items():
            if n > MAX_PER_COLUMN:
                out.append(
                    Problem(
                        self.batch_id,
                        file,
                        f"... and {n - MAX_PER_COLUMN} more problems in this file and column (not listed)",
                        self._trial_of[(file, column)],
                        None,
                        column,
                    )
                )
        return out


def group_warnings(warnings: Sequence[tuple[Path, str]]) -> list[str]:
    """One line per kind of warning, naming its files (a few, then a count): not one per file."""
    by_msg: dict[str, list[Path]] = {}
    for path, msg in warnings:
        by_msg.setdefault(msg, []).append(path)
    lines = []
    for msg, paths in by_msg.items():
        if len(paths) == 1:
            lines.append(f"{paths[0]}: {msg}")
        else:
            names = ", ".join(p.name for p in paths[:3]) + (
                f" and {len(paths) - 3} more" if len(paths) > 3 else ""
            )
            lines.append(f"{paths[0].parent}: {msg}: {names}")
    return lines
