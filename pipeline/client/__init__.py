"""The needle-insertion simulator's client: fetch an angle's registered force model, run it live.

    from pipeline.client import ForceClient

    client = ForceClient.from_registry(30)          # models:/needle-force-30@champion, cached locally
    client.check_stream(["fsr1", "fsr2", "fsr3"], 30.0)
    client.reset()                                  # at the start of every insertion
    frame = client.step([0.61, 0.58, 0.70], t_s=0.0)  # one 30 Hz sample -> Frame(t_s, force_n, cue)

`fetch` (module `cache`) keeps one copy per (model, alias) under the cache folder and falls back to
it, with a warning, when the registry cannot be reached, so a simulator keeps working offline. A
client made by `from_registry` (module `force`) follows its alias: `reset()` asks the registry where
the alias points at most once every `poll_s` seconds and, if it moved, swaps in the new version
between insertions (`refresh()` does it on demand); `step()` never talks to the registry.

The model is the ONNX graph of `pipeline.modelling.export` run by onnxruntime; nothing is unpickled.
Importing this package and running a client needs numpy, pyyaml, onnxruntime and mlflow-skinny only
(mlflow and onnxruntime are imported when first needed). Replaying recorded trials, which needs
pandas, is `pipeline.client.replay`, not imported here.
"""

from pipeline.client.cache import (
    CACHE_ENV,
    DEFAULT_CACHE,
    VERSION_FILE,
    ModelNotFound,
    default_cache_dir,
    fetch,
)
from pipeline.client.force import DEFAULT_POLL_S, ForceClient, Frame, StreamMismatch
from pipeline.registry.store import RegistryUnreachable

__all__ = [
    "CACHE_ENV",
    "DEFAULT_CACHE",
    "DEFAULT_POLL_S",
    "VERSION_FILE",
    "ForceClient",
    "Frame",
    "ModelNotFound",
    "RegistryUnreachable",
    "StreamMismatch",
    "default_cache_dir",
    "fetch",
]
