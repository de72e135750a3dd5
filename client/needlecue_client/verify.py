"""What makes a copy runnable: `Describe` checks a downloaded version and says what version.json
keeps of it (a broken version raises ValueError), `Verify` checks a cached copy against its
version.json (what is wrong, or None), for a force model and for a unit's calibration."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from needlecue_client.folder import MLMODEL, ONNX_FILE, open_model
from needlecue_runtime.registry import store
from needlecue_runtime.unit_calibration import FILE as UNIT_FILE
from needlecue_runtime.unit_calibration import read_unit
from needlecue_runtime.vocab import file_sha256

# What a simulator runs of a force model: its description and its ONNX (not the environment files)
MODEL_FILES = (MLMODEL, ONNX_FILE)


Describe = Callable[[Path, Any], dict[str, Any]]  # (downloaded folder, ModelVersion) -> version.json fields


Verify = Callable[[Path, dict[str, Any]], str | None]  # (cached folder, its version.json) -> what is wrong


def _copy_problem(folder: Path, info: dict[str, Any], name: str, file: str, sha_key: str) -> str | None:
    """What makes a cached copy of `name` unusable, as far as version.json and `file` tell."""
    if info.get("name") != name:
        return f"its version.json is of {info.get('name')!r}, not {name!r}"
    if not info.get("version"):
        return "its version.json names no version"
    if not (folder / file).is_file():
        return f"it has no {file}"
    if file_sha256([folder / file]) != info.get(sha_key):
        return f"{file} is not the file fetched (its sha256 differs from version.json's): changed or damaged"
    return None


def model_problem(name: str, angle_deg: float) -> Verify:
    """A cached force model: the copy of `name`, its ONNX as fetched, its MLmodel readable and of that
    angle and checkpoint."""

    def problem(folder: Path, info: dict[str, Any]) -> str | None:
        if why := _copy_problem(folder, info, name, ONNX_FILE, "onnx_sha256"):
            return why
        try:
            meta, _ = open_model(folder)  # the graph and its description, as registered
        except (OSError, ValueError) as e:
            return str(e)
        if float(meta.get("angle_deg", "nan")) != float(angle_deg):
            return f"its MLmodel is of the {meta.get('angle_deg')}° model, not {angle_deg:g}°"
        if meta.get("checkpoint_sha256") != info.get("checkpoint_sha256"):
            return "its MLmodel names another checkpoint than the one fetched"
        return None

    return problem


def unit_problem(name: str, unit_id: str) -> Verify:
    """A cached unit calibration: the copy of `name`, its document as fetched and of that unit."""

    def problem(folder: Path, info: dict[str, Any]) -> str | None:
        if why := _copy_problem(folder, info, name, UNIT_FILE, "calibration_sha256"):
            return why
        try:
            doc = read_unit(folder / UNIT_FILE)
        except (OSError, ValueError) as e:
            return f"its calibration document is unusable ({e})"
        if doc.unit_id != unit_id or info.get("unit_id") != unit_id:
            return f"it holds the calibration of unit {doc.unit_id!r}, not {unit_id!r}"
        return None

    return problem


def model_info(folder: Path, mv: Any) -> dict[str, Any]:
    """What version.json says of a downloaded force model, beyond the version itself."""
    missing = [f for f in MODEL_FILES if not (folder / f).is_file()]
    if missing:  # a broken registered model is an error, not a reason to go offline
        raise ValueError(f"{mv.name} version {mv.version} ({mv.source}) has no {' or '.join(missing)}")
    meta, _ = open_model(folder)  # ModelRefused (a ValueError): the registered version is broken
    return {"checkpoint_sha256": meta.get("checkpoint_sha256"), "onnx_sha256": meta["onnx_sha256"]}


def signed_model_fields(folder: Path, mv: Any) -> dict[str, Any]:
    """What the lab's signed manifest says of a published force model (its checkpoint and graph), once
    the graph is the one it names. Every file's hash was checked against the manifest already; the
    MLmodel is parsed once, when the client opens the folder and checks it against the graph."""
    missing = [f for f in MODEL_FILES if not (folder / f).is_file()]
    if missing:
        raise ValueError(f"{mv.name} version {mv.version} ({mv.source}) has no {' or '.join(missing)}")
    described = {k: mv.describe.get(k) for k in ("checkpoint_sha256", "onnx_sha256")}
    if file_sha256([folder / ONNX_FILE]) != described["onnx_sha256"]:
        raise ValueError(f"its {ONNX_FILE} is not the graph its manifest describes (onnx_sha256)")
    return described


def unit_info(unit_id: str) -> Describe:
    """What version.json says of a downloaded unit calibration: a checked document of that unit."""

    def info(folder: Path, mv: Any) -> dict[str, Any]:
        path = folder / UNIT_FILE
        if not path.is_file():
            raise ValueError(f"{mv.name} version {mv.version} ({mv.source}) has no {UNIT_FILE}")
        sha, registered = (
            file_sha256([path]),
            (getattr(mv, "tags", None) or {}).get(store.CALIBRATION_SHA_TAG),
        )
        if sha != registered:  # the document's bytes as registered, or a version not to run
            raise ValueError(
                f"{mv.name} version {mv.version}: its {UNIT_FILE} (sha256 {sha[:12]}…) is not the document "
                f"registered (tag {store.CALIBRATION_SHA_TAG}: {registered!r}); register it again with "
                "`needlecue calibrate`"
            )
        doc = read_unit(path)
        if doc.unit_id != unit_id:
            raise ValueError(f"{mv.name} version {mv.version} holds the calibration of unit {doc.unit_id!r}")
        return {"unit_id": unit_id, "calibration_sha256": sha}

    return info
