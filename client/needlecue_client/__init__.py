"""The needle-insertion simulator's client: fetch an angle's registered force model and the estimator
unit's calibration, run them live.

    from needlecue_client import ForceClient

    client = ForceClient.from_registry(30, unit_id="est-042")  # models:/needle-force-30@champion
    client.calibrated                               # True: est-042's calibration fits this model
    client.check_stream(["fsr1", "fsr2", "fsr3"], 30.0)
    client.reset()                                  # at the start of every insertion
    frame = client.step([0.61, 0.58, 0.70], t_s=0.0)  # one 30 Hz sample -> Frame(t_s, force_n, cue)

Every estimator unit differs; the shared models read a unit through its calibration, registered as
`needle-unit-<unit_id>@current` by `needlecue calibrate BATCH_DIR` (or the pipeline's `register`
stage) from one short calibration batch. The client applies it when it was made with the loaded model
(its checkpoint sha256). Otherwise (no `unit_id`, the unit not registered, a calibration made with
other models, say an older champion, offline without a cached calibration)
the client is uncalibrated: an `UncalibratedUnit` warning names the unit, the reason and the fix, the
force is still given, and no cues (`Frame.cue` is None, `has_cues` False) unless
`cues_uncalibrated=True`. `from_dir(model_dir, calibration=...)` takes a calibration.json (or the
document) instead of fetching one.

`fetch` and `fetch_unit` (module `cache`) keep one copy per (model, alias) under the cache folder and
fall back to it, with a warning, when the registry cannot be reached, so a simulator keeps working
offline. A client made by `from_registry` (module `force`) follows its alias: `reset()` asks the
registry where the alias points at most once every `poll_s` seconds and, if it moved, swaps in the new
version between insertions and decides the unit's calibration again (`refresh()` does it on demand; it
also picks up a new calibration of the unit); `step()` never talks to the registry.

The model is the ONNX graph of `pipeline.modelling.export` run by onnxruntime; nothing is unpickled.
Importing this package and running a client needs numpy, pyyaml, onnxruntime and mlflow-skinny only
(mlflow and onnxruntime are imported when first needed). Replaying recorded trials, which needs
pandas, is `needlecue_client.replay`, not imported here.

Nothing runs unchecked (module `folder`): a model folder's graph and its description (input settings,
cue pack) must be the ones registered, fetched or cached, else `ModelRefused`; a unit's calibration
must be the document registered. `from_dir(..., unverified=True)` runs a folder anyway, loudly.
"""

from needlecue_client.cache import fetch, fetch_unit
from needlecue_client.copies import (
    CACHE_ENV,
    DEFAULT_CACHE,
    VERSION_FILE,
    CachedCopyRefused,
    ModelNotFound,
    default_cache_dir,
)
from needlecue_client.folder import ModelFolderError, ModelRefused
from needlecue_client.force import DEFAULT_POLL_S, ForceClient, Frame, StreamMismatch, UncalibratedUnit
from needlecue_runtime.registry.store import UNIT_ALIAS, RegistryUnreachable

__all__ = [
    "CACHE_ENV",
    "DEFAULT_CACHE",
    "DEFAULT_POLL_S",
    "UNIT_ALIAS",
    "VERSION_FILE",
    "CachedCopyRefused",
    "ForceClient",
    "Frame",
    "ModelFolderError",
    "ModelNotFound",
    "ModelRefused",
    "RegistryUnreachable",
    "StreamMismatch",
    "UncalibratedUnit",
    "default_cache_dir",
    "fetch",
    "fetch_unit",
]
