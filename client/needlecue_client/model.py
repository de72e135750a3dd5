"""One fetched force model, opened once and never changed: its ONNX session, its description (the
`needlecue` block of its MLmodel) and what a stream must be to feed it. A client that follows an alias
swaps one `Model` for another; it never edits one."""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from needlecue_client.copies import read_version
from needlecue_client.folder import ONNX_FILE, open_model
from needlecue_runtime.features import ModelInputs, spec_of

# One logger for the whole client, named as before it was split into modules (log configs keep working).
log = logging.getLogger("needlecue_client")


class StreamMismatch(ValueError):
    """The estimator stream's channels or rate are not those the model was trained on."""


@dataclass(frozen=True)
class Model:
    """A model folder, checked and loaded (`open`). `version` is the version.json of a fetched folder
    (name, version, alias, run_id, source, ...; None for a bare folder); `metadata` the whole
    `needlecue` block."""

    model_dir: Path
    metadata: dict[str, Any]
    session: Any  # onnxruntime.InferenceSession
    version: dict[str, Any] | None

    @classmethod
    def open(cls, model_dir: Path, unverified: bool = False) -> Model:
        """Check the folder (`needlecue_client.folder.open_model`: refused unless it is what was
        registered) and that its graph reads what its description says."""
        model_dir = Path(model_dir)
        metadata, session = open_model(model_dir, unverified=unverified)
        model = cls(model_dir, metadata, session, read_version(model_dir))
        inputs = session.get_inputs()
        names = metadata["graph_inputs"]
        shapes = [tuple(i.shape[1:]) for i in inputs[:2]]
        if [i.name for i in inputs] != names or any(s != model.input_shape for s in shapes):
            found = [(i.name, i.shape) for i in inputs]
            raise ValueError(
                f"{model_dir / ONNX_FILE}: inputs {found} do not match its MLmodel metadata "
                f"({names[:2]} of shape (batch, {', '.join(map(str, model.input_shape))}))"
            )
        out = session.get_outputs()[0]
        if out.name != metadata["output"] or tuple(out.shape[1:]) != (len(model.targets),):
            raise ValueError(
                f"{model_dir / ONNX_FILE}: output {out.name} of shape {out.shape} does not match its MLmodel "
                f"metadata ({metadata['output']} of shape (batch, {len(model.targets)}): "
                f"{', '.join(model.targets)})"
            )
        return model

    @property
    def kind(self) -> str:
        return str(self.metadata["kind"])

    @property
    def angle_deg(self) -> float:
        """The preset angle the model was trained at."""
        return float(self.metadata["angle_deg"])

    @property
    def channels(self) -> tuple[str, ...]:
        """The estimator channels it reads, in the order `step` takes volts."""
        return tuple(self.metadata["channels"])

    @property
    def targets(self) -> tuple[str, ...]:
        """The force axes the model gives, in the order of `step`'s force: those its reference sensor
        recorded, a non-empty subset of fx, fy, fz in that order (("fz",) for a load cell's model)."""
        return tuple(self.metadata["targets"])

    @property
    def rate_hz(self) -> float | None:
        rate = self.metadata.get("rate_hz")
        return None if rate is None else float(rate)

    @property
    def window(self) -> int:
        """Samples of history per prediction (1 for ls and fnn)."""
        return int(self.metadata["window"])

    @property
    def inputs(self) -> ModelInputs:
        """How its graph computes the model's inputs from volts (its rest period: `rest_s`)."""
        return spec_of(self.metadata.get("inputs"))

    @property
    def input_shape(self) -> tuple[int, ...]:
        """(window, channels): the raw samples a graph row reads (one for ls and fnn)."""
        return (self.window, len(self.channels))

    @property
    def cue_pack(self) -> dict[str, Any] | None:
        return self.metadata.get("cues")

    @property
    def name(self) -> str:
        """`needle-force-30 v3 (lstm)`, or the folder for an unregistered copy."""
        if self.version:
            return f"{self.version.get('name')} v{self.version.get('version')} ({self.kind})"
        return f"{self.model_dir} ({self.kind})"

    @property
    def version_key(self) -> tuple[str, Any] | None:
        """(version, source) of a fetched model: the source tells two stores' "v1" apart."""
        v = self.version
        return None if v is None else (str(v.get("version")), v.get("source"))

    def cue_tracker(self) -> Any | None:
        """A fresh cue tracker of the model's cue pack; None without a usable pack (force without cues
        beats no force at all)."""
        pack = self.cue_pack
        if pack is None:
            return None
        from needlecue_runtime.cues.pack import as_pack, pack_format_problem
        from needlecue_runtime.cues.tracker import CueTracker

        problem = pack_format_problem(pack)
        if problem:
            log.warning("%s: no cues: %s", self.model_dir, problem)
            return None
        typed = as_pack(pack, f"{self.model_dir}: its cue pack")  # a missing or renamed field fails here
        # the pack's standard profile is compared with `step`'s force: the same axes, in the same order
        profile = typed.standard_profile
        if profile is not None and list(profile.axes) != list(self.targets):
            log.warning(
                "%s: no cues: the cue pack's standard profile is of %s, the model gives %s",
                self.model_dir,
                list(profile.axes),
                list(self.targets),
            )
            return None
        if list(typed.channels) != list(self.channels):
            raise ValueError(
                f"{self.model_dir}: the cue pack reads channels {typed.channels}, "
                f"the model {list(self.channels)}"
            )
        # the paper-method thresholds were calibrated per model kind: use this model's if there
        kinds = typed.thresholds.profile
        return CueTracker(typed, self.angle_deg, model_kind=self.kind if self.kind in kinds else None)

    def check_stream(self, channels: Sequence[str], rate_hz: float | None, rel_tol: float = 0.05) -> None:
        """Raise `StreamMismatch` unless the stream delivers the model's channels (same order) at its
        rate (within `rel_tol`)."""
        problems = []
        if tuple(channels) != self.channels:
            missing = [c for c in self.channels if c not in channels]
            extra = [c for c in channels if c not in self.channels]
            detail = f"missing {missing}" if missing else ""
            detail += (", " if detail and extra else "") + (f"extra {extra}" if extra else "")
            problems.append(
                f"channels: the model reads {list(self.channels)}, the stream has {list(channels)} "
                f"({detail or 'same channels in another order: pass volts in the model order'})"
            )
        rate = self.rate_hz if rate_hz is None else rate_hz
        if self.rate_hz is not None and not (
            math.isfinite(rate) and abs(rate - self.rate_hz) <= rel_tol * self.rate_hz
        ):
            problems.append(
                f"rate: the model was trained at {self.rate_hz:.3g} Hz, the stream runs at {rate:.3g} Hz "
                f"(tolerance {rel_tol:.0%})"
            )
        if problems:
            raise StreamMismatch(
                f"stream does not fit {self.name}, angle {self.angle_deg:g}°: " + "; ".join(problems)
            )

    def misfit(self, new: Model, stream: tuple[Sequence[str], float | None, float] | None) -> str | None:
        """Why `new` cannot take this model's place on `stream` (channels, rate, tolerance; None: the
        stream this model has been fed, its own channels and rate); None if it can."""
        if new.angle_deg != self.angle_deg or new.targets != self.targets:
            return (
                f"it is for {new.angle_deg:g}° and gives {list(new.targets)}, "
                f"this client {self.angle_deg:g}° and {list(self.targets)}"
            )
        channels, rate_hz, rel_tol = stream or (self.channels, self.rate_hz, 0.05)
        try:
            new.check_stream(channels, rate_hz, rel_tol)
        except StreamMismatch as e:
            return str(e)
        return None
