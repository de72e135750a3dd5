"""A model folder as a simulator runs it (MLmodel + model.onnx), checked before anything runs.

What is checked (`open_model`):

- every field of the MLmodel's `needlecue` block the client reads has the type and range it needs:
  a bad one is one line naming the file, the field and what was expected (`ModelFolderError`);
- the graph is the one the description names: its sha256 is the block's `onnx_sha256`;
- the description is the one registered with the graph: the graph's own metadata holds the sha256
  of the block (`needlecue_runtime.vocab.description_sha256`), so an input setting, the cue pack or any other
  field edited after registration is found, online or offline.

A folder that fails is refused (`ModelRefused`), unless the caller asks for `unverified`: then only
the fields are checked and a loud warning says what is not. onnxruntime is imported when first needed.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from needlecue_runtime.registry import store
from needlecue_runtime.vocab import (
    AXES,
    DEPLOY_FORMAT,
    DEPLOY_FORMATS,
    INPUT_NAMES,
    axes_in_order,
    description_sha256,
)

log = logging.getLogger("needlecue_client")

MLMODEL = "MLmodel"
ONNX_FILE = "model.onnx"
# the graph's own description (pipeline.modelling.export.to_onnx) and the fields it repeats
GRAPH_KEY = "needlecue"
SHA_HEX = 64


class ModelFolderError(ValueError):
    """A model folder whose description cannot be read: the file, the field, what was expected."""


class ModelRefused(ModelFolderError):
    """A model folder that fails its check: its graph or its description is not what was registered."""


def _number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def _names(value: Any) -> bool:
    return isinstance(value, list) and bool(value) and all(isinstance(v, str) and v for v in value)


# field -> (does the value fit, what was expected); checked in this order
FIELDS: dict[str, tuple[Any, str]] = {
    "kind": (lambda v: isinstance(v, str) and bool(v), "a model kind (ls, fnn, lstm)"),
    "angle_deg": (_number, "the preset angle in degrees (a number)"),
    "channels": (
        lambda v: _names(v) and len(set(v)) == len(v),
        "a list of distinct channel names, e.g. [fsr1, fsr2, fsr3]",
    ),
    "targets": (
        axes_in_order,
        f"a non-empty list of force axes among {', '.join(AXES)}, in that order, e.g. [fx, fy, fz] or [fz]",
    ),
    "rate_hz": (lambda v: v is None or (_number(v) and v > 0), "the sample rate in Hz (> 0) or null"),
    "window": (lambda v: isinstance(v, int) and not isinstance(v, bool) and v >= 1, "an integer >= 1"),
    "graph_inputs": (lambda v: v == list(INPUT_NAMES), f"the graph's inputs {list(INPUT_NAMES)}"),
    "output": (lambda v: isinstance(v, str) and bool(v), "the graph's output name"),
    "checkpoint_sha256": (
        lambda v: isinstance(v, str) and len(v) == SHA_HEX,
        "the checkpoint's sha256 (64 hex digits)",
    ),
    "inputs": (lambda v: v is None or isinstance(v, Mapping), "the input settings (a mapping)"),
    "cues": (lambda v: v is None or isinstance(v, Mapping), "a cue pack (a mapping) or null"),
}


def read_metadata(model_dir: Path) -> dict[str, Any]:
    """The `needlecue` block of a model folder's MLmodel (plain YAML: no mlflow import, no pickle),
    every field the client reads checked (`ModelFolderError` naming the file and the field)."""
    mlmodel = model_dir / MLMODEL
    if not mlmodel.is_file():
        raise FileNotFoundError(f"{model_dir} is not a fetched model folder: it has no MLmodel file")
    try:
        meta = store.mlmodel_metadata(mlmodel).get("needlecue")
    except ValueError as e:
        raise ModelFolderError(f"{mlmodel}: {e}") from e
    if not isinstance(meta, dict) or meta.get("format") not in DEPLOY_FORMATS:
        found = meta.get("format") if isinstance(meta, dict) else None
        raise ModelFolderError(
            f"{mlmodel}: no {DEPLOY_FORMAT} block under metadata.needlecue (found format {found!r}); "
            "was this model logged with pipeline.modelling.export.log_onnx_model?"
        )
    if meta["format"] != DEPLOY_FORMAT:
        raise ModelFolderError(
            f"{mlmodel}: a {meta['format']} model, whose graph does not take what the estimator sends "
            f"as this client feeds it; this client runs {DEPLOY_FORMAT} graphs: register it again "
            "(dvc repro)"
        )
    for field, (fits, expected) in FIELDS.items():
        if field not in meta:
            raise ModelFolderError(f"{mlmodel}: field needlecue.{field} is missing; expected {expected}")
        if not fits(meta[field]):
            raise ModelFolderError(
                f"{mlmodel}: field needlecue.{field} is {meta[field]!r}; expected {expected}"
            )
    return meta


def _graph_description(session: Any) -> dict[str, Any]:
    """The description the graph carries in its own metadata ({} if none)."""
    text = session.get_modelmeta().custom_metadata_map.get(GRAPH_KEY)
    try:
        found = json.loads(text) if text else {}
    except ValueError:
        return {}
    return found if isinstance(found, dict) else {}


def _graph_problem(folder: Path, meta: Mapping[str, Any], graph: bytes) -> str | None:
    """Why `graph` is not the one the description names (None: it is); before it is parsed."""
    mlmodel, onnx_file = folder / MLMODEL, folder / ONNX_FILE
    named = meta.get("onnx_sha256")
    if meta.get("format") != DEPLOY_FORMAT or not isinstance(named, str):
        return (
            f"{mlmodel}: field needlecue.onnx_sha256 is missing (format {meta.get('format')!r}): logged "
            f"before {DEPLOY_FORMAT}, whose graph and description vouch for each other; register it "
            "again (dvc repro)"
        )
    sha = hashlib.sha256(graph).hexdigest()
    if sha != named:
        return (
            f"{onnx_file}: its sha256 {sha[:12]}… is not the {named[:12]}… that {MLMODEL} "
            "(needlecue.onnx_sha256) names: the graph was changed, damaged or swapped"
        )
    return None


def _description_problem(folder: Path, meta: Mapping[str, Any], session: Any) -> str | None:
    """Why the description is not the one registered with the graph (None: it is)."""
    own = _graph_description(session)
    if own.get("description_sha256") == description_sha256(meta):
        return None
    changed = [f"needlecue.{k}" for k, v in own.items() if k in meta and meta[k] != v]
    verb = "differs" if len(changed) == 1 else "differ"
    which = f"; {', '.join(changed)} {verb} from the graph's own" if changed else ""
    return (
        f"{folder / MLMODEL}: the needlecue block is not the description registered with {ONNX_FILE} "
        f"(a field was changed after registration: input settings, cue pack, ...{which})"
    )


def open_model(model_dir: Path, *, unverified: bool = False) -> tuple[dict[str, Any], Any]:
    """(the checked description, an onnxruntime session of the graph) of a model folder: refused
    (`ModelRefused`) unless graph and description are what was registered, or, with `unverified`,
    run after a loud warning. One thread, sequential: a simulator steps one frame at a time."""
    import onnxruntime as ort

    model_dir = Path(model_dir)
    meta = read_metadata(model_dir)
    onnx_file = model_dir / ONNX_FILE
    if not onnx_file.is_file():
        raise FileNotFoundError(f"{model_dir} has no {ONNX_FILE}")
    graph = onnx_file.read_bytes()  # read once: the bytes checked are the bytes run
    if not unverified and (why := _graph_problem(model_dir, meta, graph)):
        raise ModelRefused(why)  # before parsing: a damaged file never reaches the parser
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 1  # one frame at a time: threads would only add hand-off latency
    opts.inter_op_num_threads = 1
    opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    try:
        session = ort.InferenceSession(graph, opts, providers=["CPUExecutionProvider"])
    except Exception as e:  # onnxruntime's own error types: a file that is not a graph it can run
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise ModelFolderError(f"{onnx_file}: not an ONNX graph onnxruntime can run ({first})") from e
    if unverified:
        log.warning(
            "UNVERIFIED model %s: its graph and description were not checked against what was "
            "registered; its forces and cues may be wrong",
            model_dir,
        )
    elif why := _description_problem(model_dir, meta, session):
        raise ModelRefused(why)
    return meta, session
