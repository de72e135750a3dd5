"""What the typed JSON documents between stages share (evaluation.json: `pipeline.metrics.document`;
the cue evaluation: `pipeline.cues.document`): a frozen model that forbids unknown fields, and one
writer and one reader per file that check it, naming the file and the field on failure."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Generic, TypeVar

from pydantic import BaseModel, ConfigDict, TypeAdapter, ValidationError

from needlecue_runtime.vocab import dump_json

T = TypeVar("T")
Number = float | None  # None: cannot be computed (NaN is not JSON)


class Document(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")


@dataclass(frozen=True)
class DocumentFile(Generic[T]):
    """How one kind of document is checked (`adapter`), written (rounded to `digits`, sorted keys,
    no NaN) and named in errors (`what`, and the `stage` that writes it)."""

    adapter: TypeAdapter[T]
    what: str  # "an evaluation"
    stage: str  # the stage that writes it: what to rerun
    digits: int
    indent: int = 2

    def text(self, doc: Any) -> str:
        return dump_json(doc, self.digits, self.indent)

    def write(self, path: Path, doc: Any) -> T:
        """Write `doc` after checking it is a whole document (ValueError naming the fields otherwise,
        and nothing written); returns it as given, unrounded."""
        checked = self._parse(doc, f"{path} (being written)")
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(self.text(doc))
        return checked

    def read(self, path: Path) -> T:
        """The document at `path`; FileNotFoundError, or ValueError naming the file and fields."""
        try:
            doc = json.loads(path.read_text())
        except ValueError as e:
            raise ValueError(f"{path}: not JSON ({e}); rerun the {self.stage} stage") from e
        return self._parse(doc, str(path))

    def _parse(self, doc: Any, where: str) -> T:
        try:
            return self.adapter.validate_python(doc)
        except ValidationError as e:
            raise ValueError(
                f"{where}: not {self.what} this needlecue reads (rerun the {self.stage} stage): {e}"
            ) from e
