"""Reading the split stage's output, `DATA_DIR/<angle>/<split>.parquet`: the one reader every later
stage uses, each file read at most once."""

from __future__ import annotations

import json
from collections.abc import Iterable
from pathlib import Path

import pandas as pd

from needlecue_runtime.frontend import Circuit, circuit_key, declared
from needlecue_runtime.vocab import CALIBRATION, SPLITS, sorted_angles

FRONT_ENDS = "front_ends.json"  # in each angle folder (and calibration/): {unit_id: its circuit or null}


def _is_angle(name: str) -> bool:
    try:
        float(name)
    except ValueError:
        return False
    return True


class SplitFiles:
    """The processed split files, `DATA_DIR/<angle>/<split>.parquet`, each read at most once."""

    def __init__(self, data_dir: Path) -> None:
        self.data_dir = Path(data_dir)
        self._frames: dict[tuple[str, str], pd.DataFrame] = {}

    def path(self, angle: str, split: str) -> Path:
        return self.data_dir / angle / f"{split}.parquet"

    def angles(self) -> list[str]:
        """Every angle folder that holds a split file (other folders are not angles: skipped)."""
        if not self.data_dir.is_dir():
            raise FileNotFoundError(f"{self.data_dir}: no such folder (run the split stage first)")
        return sorted_angles(
            p.name
            for p in self.data_dir.iterdir()
            if _is_angle(p.name) and any(self.path(p.name, s).is_file() for s in SPLITS)
        )

    def frame(self, angle: str, split: str) -> pd.DataFrame:
        """One split file's rows; FileNotFoundError if the split stage did not write it."""
        if (angle, split) not in self._frames:
            path = self.path(angle, split)
            if not path.is_file():
                raise FileNotFoundError(f"{path}: missing (run the split stage first)")
            self._frames[angle, split] = pd.read_parquet(path)
        return self._frames[angle, split]

    def front_ends(self) -> dict[str, Circuit | None]:
        """{unit_id: its declared circuit, or None} of every unit in every angle folder and in the
        calibration folder (the split stage's `front_ends.json` files)."""
        out: dict[str, Circuit | None] = {}
        for folder in [*(self.data_dir / a for a in self.angles()), self.data_dir / CALIBRATION]:
            out.update(front_ends(folder))
        return dict(sorted(out.items()))

    def by_angle(self, split: str) -> dict[float, pd.DataFrame]:
        """{angle: frame} of one split, over the angle folders that have it, in angle order."""
        return {float(a): self.frame(a, split) for a in self.angles() if self.path(a, split).is_file()}


def unit_roles(data_dir: Path) -> dict[str, str]:
    """{unit_id: "training" | "new"} from the split stage's manifest (its `units`); {} without one."""
    path = Path(data_dir) / "manifest.json"
    if not path.is_file():
        return {}
    units = json.loads(path.read_text()).get("units") or {}
    return {str(u): str(entry.get("role", "new")) for u, entry in units.items()}


def front_ends(folder: Path) -> dict[str, Circuit | None]:
    """{unit_id: the circuit it declares, or None} of the units with trials in one processed folder
    (an angle's, or calibration/); {} for a folder written before front ends were data."""
    path = Path(folder) / FRONT_ENDS
    if not path.is_file():
        return {}
    try:
        return {str(u): declared(c) for u, c in json.loads(path.read_text()).items()}
    except (ValueError, AttributeError) as e:
        raise ValueError(f"{path}: not a map of unit ids to front ends: {e}") from e


def common_front_end(circuits: dict[str, Circuit | None], units: Iterable[str]) -> Circuit | None:
    """The one circuit `units` all declare, or None if any declares none; ValueError naming them if
    they declare different ones (the conductance inputs of one model need one circuit)."""
    found = {u: circuits.get(u) for u in sorted(set(units))}
    if not found or any(c is None for c in found.values()):
        return None
    if len({circuit_key(c) for c in found.values()}) > 1:
        raise ValueError(
            f"the units {', '.join(found)} declare different front ends: one model's conductance inputs "
            "read one circuit; use inputs kind volts or rest_volts, or train on units of one design"
        )
    return next(iter(found.values()))
