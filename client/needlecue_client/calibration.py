"""Which calibration of the estimator unit applies to a model: the registered one
(`needle-unit-<unit_id>@current`, fetched and cached like the models) or one given as a document, and
whether it was made with this very model. Pure decisions but `registered`, which fetches."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from needlecue_client.cache import fetch_unit
from needlecue_client.copies import ModelNotFound, read_version
from needlecue_client.model import Model
from needlecue_runtime.features import InputTransform
from needlecue_runtime.registry import store
from needlecue_runtime.unit_calibration import FILE as UNIT_FILE
from needlecue_runtime.unit_calibration import UnitCalibration, parse_unit, read_unit, transform_for
from needlecue_runtime.vocab import angle_name, file_sha256

CALIBRATE_FIX = "record a calibration batch with the unit and run `needlecue calibrate BATCH_DIR`"
NO_UNIT = "no estimator unit named (unit_id)"


@dataclass(frozen=True)
class Source:
    """A calibration document and where it came from (a version.json, or a file), or why there is
    none (`problem`)."""

    doc: UnitCalibration | None
    info: dict[str, Any] | None
    problem: str | None = None

    @property
    def seen(self) -> tuple[str, Any] | None:
        """(version, source) of a registered document: a poll that finds it again fetches nothing."""
        return (
            None
            if not self.info or "source" not in self.info
            else (str(self.info.get("version")), self.info.get("source"))
        )


@dataclass(frozen=True)
class Decision:
    """The unit's calibration for one model: the transform applied to every sample (None:
    uncalibrated, `reason` says why), the circuit a calibrated unit declared, the document's info."""

    transform: InputTransform | None
    reason: str | None
    circuit: Any
    calibration: dict[str, Any] | None
    doc: UnitCalibration | None

    @property
    def calibrated(self) -> bool:
        return self.transform is not None


def given(
    calibration: Path | str | Mapping[str, Any] | UnitCalibration | None, unit_id: str | None
) -> tuple[Source, str | None]:
    """The source of a calibration given to `from_dir` (a calibration.json path, read and checked, or
    the document itself, checked) and the client's unit (the document's; another `unit_id` is a
    ValueError)."""
    if calibration is None:
        problem = NO_UNIT if unit_id is None else "no calibration document was given (calibration=...)"
        return Source(None, None, problem), unit_id
    if isinstance(calibration, UnitCalibration):
        doc = calibration
        info: dict[str, Any] = {"unit_id": doc.unit_id}
    elif isinstance(calibration, Mapping):
        doc = parse_unit(dict(calibration), "the calibration document given")
        info = {"unit_id": doc.unit_id}
    else:
        path = Path(calibration)
        doc = read_unit(path)
        info = {"unit_id": doc.unit_id, "path": str(path), "calibration_sha256": file_sha256([path])}
    if unit_id is not None and doc.unit_id != unit_id:
        raise ValueError(f"the calibration given is of unit {doc.unit_id!r}, not {unit_id!r}")
    return Source(doc, info), doc.unit_id


def registered(unit_id: str | None, fetch_kwargs: Mapping[str, Any]) -> Source:
    """The registered calibration of the unit, fetched (or its cached copy when offline)."""
    if unit_id is None:
        return Source(None, None, NO_UNIT)
    name = store.unit_model_name(unit_id)
    try:
        folder = fetch_unit(unit_id, **fetch_kwargs)
        return Source(read_unit(folder / UNIT_FILE), read_version(folder))
    except ModelNotFound:
        return Source(None, None, f"it has no registered calibration ({name}@{store.UNIT_ALIAS})")
    except store.RegistryUnreachable as e:
        return Source(None, None, f"the registry cannot be reached and no calibration is cached ({e})")
    except ValueError as e:  # a broken registered document
        return Source(None, None, f"its registered calibration cannot be used: {e}")


def decide(model: Model, source: Source) -> Decision:
    """Whether `source`'s document applies to `model` (made with this very model, for its inputs)."""
    transform, reason = (None, source.problem) if source.doc is None else transform_of(model, source.doc)
    if transform is None:
        return Decision(None, reason or "unknown", None, None, source.doc)
    # a calibrated unit that declared its circuit is read through it (else the model's)
    return Decision(transform, None, source.doc.circuit, dict(source.info or {}), source.doc)


def transform_of(model: Model, doc: UnitCalibration) -> tuple[InputTransform | None, str | None]:
    """The unit's transform for `model`, or (None, why it does not apply)."""
    angle, sha = angle_name(model.angle_deg), str(model.metadata.get("checkpoint_sha256"))
    transform = transform_for(doc, model.kind, angle, sha)
    if transform is None:
        transforms = doc.transforms
        made = transforms[model.kind].models if model.kind in transforms else {}
        if model.kind not in transforms:
            found = ", ".join(sorted(transforms)) or "none"
            return None, f"its calibration has no transform for {model.kind} models (it has {found})"
        if angle not in made:
            return None, f"its calibration was not made with a {model.kind} model at {angle}°"
        return None, (
            f"its calibration was made with another {model.kind} model at {angle}° (checkpoint "
            f"{str(made[angle])[:12]}, this model's {sha[:12]}): calibrate the unit for the new model"
        )
    if transform.n != len(model.channels):
        return (
            None,
            f"its {model.kind} transform maps {transform.n} inputs, the model reads {len(model.channels)}",
        )
    return transform, None


def about(info: Mapping[str, Any] | None) -> str:
    """`needle-unit-est-101 v2`, or the file, of a calibration's version info."""
    if not info:
        return "a calibration given"
    if info.get("name"):
        return f"{info['name']} v{info.get('version')}"
    return str(info.get("path") or f"a calibration of {info.get('unit_id')}")
