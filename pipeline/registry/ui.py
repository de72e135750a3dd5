"""MLflow's UI on the registry, opened where the lab compares models: the runs of `needle-force` as
model training, in the view `store.experiment_id` saves on the experiment (external NRMSE, test
NRMSE, angle and model type; best first). A tracking server serves its own UI; the project's sqlite
store is served by `mlflow server` on this machine."""

from __future__ import annotations

import shutil
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from needlecue_runtime.registry.store import EXPERIMENT, RegistryUnreachable, ui_link

if TYPE_CHECKING:
    from mlflow import MlflowClient


def is_server(uri: str) -> bool:
    """A tracking server (it has a UI of its own), not a store MLflow opens itself."""
    return uri.startswith(("http://", "https://"))


def runs_link(client: MlflowClient, ui_url: str) -> str:
    """The UI page of `needle-force`'s runs at `ui_url`; `RegistryUnreachable` if the store has no
    such experiment yet (nothing registered)."""
    found = client.get_experiment_by_name(EXPERIMENT)
    if found is None:
        raise RegistryUnreachable(
            f"{client.tracking_uri} has no experiment {EXPERIMENT!r}: run `dvc repro` first"
        )
    return ui_link(ui_url, str(found.experiment_id))


# What every `mlflow server` of ours adds to its environment. MLflow 3 starts a job runner with the server
# unless told not to: eight more processes (huey consumers for MLflow's GenAI jobs: prompt optimisation,
# scorers, trace roll-ups), measured here as 1.9 GB more memory and over a second more to start, each
# importing MLflow (about 2.5 CPU-s apiece). A model registry runs none of those jobs.
SERVER_ENV = {"MLFLOW_SERVER_ENABLE_JOB_EXECUTION": "false"}


def server_command(uri: str, host: str, port: int) -> list[str]:
    """`mlflow server` on the store at `uri`, one worker, bound to `host`:`port` (run it with
    `SERVER_ENV` added to its environment)."""
    mlflow = shutil.which("mlflow", path=str(Path(sys.executable).parent)) or "mlflow"
    return [
        mlflow,
        "server",
        "--backend-store-uri",
        uri,
        "--host",
        host,
        "--port",
        str(port),
        "--workers",
        "1",
    ]
