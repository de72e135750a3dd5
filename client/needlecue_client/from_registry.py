"""Fetching from an MLflow registry: a version resolved by its alias, and its files downloaded (all of
them, or those a client runs, each by itself) into a temp sibling, described and swapped in."""

from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Any

from needlecue_client.copies import ModelNotFound, staging, write_version
from needlecue_client.verify import Describe, model_info
from needlecue_runtime.registry import mlflow_env, store


def _quiet_downloads() -> contextlib.AbstractContextManager[None]:
    """No tqdm progress bar per download (it would spam a simulator's console); env restored after."""
    return mlflow_env.environment({"MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR": "false"})


def resolve(client: Any, name: str, alias: str, registry_uri: str, hint: str) -> Any:
    """The ModelVersion behind `name@alias`; `ModelNotFound` if the registry has none, and
    `RegistryUnreachable` for any other failure of the registry."""
    from mlflow.exceptions import MlflowException

    try:
        mv = store.alias_version(client, name, alias)
    except MlflowException as e:
        raise store.RegistryUnreachable(
            f"registry at {registry_uri} failed to resolve {name}@{alias}: {e}"
        ) from e
    except Exception as e:  # e.g. a connection dropped after connect() succeeded
        raise store.RegistryUnreachable(f"registry at {registry_uri}: {type(e).__name__}: {e}") from e
    if mv is None:
        raise ModelNotFound(
            f"the registry at {registry_uri} has no version of {name!r} with the alias {alias!r}; {hint}"
        )
    return mv


def download(
    mv: Any,
    alias: str,
    target: Path,
    registry_uri: str,
    describe: Describe = model_info,
    only: tuple[str, ...] | None = None,
) -> Path:
    """Download a model version (or just the files `only` names) into a temp sibling of `target`, check
    it and describe it with `describe(folder, mv)` (a broken version raises ValueError), then swap it in
    (never a partial copy)."""
    import mlflow
    from mlflow.exceptions import MlflowException

    with staging(target, alias) as tmp:
        with _quiet_downloads(), mlflow_env.fluent(registry_uri):  # models:/ URIs resolve in the registry
            # by version, not alias: the alias may move between resolving it and downloading
            try:
                if only is None:
                    mlflow.artifacts.download_artifacts(
                        artifact_uri=f"models:/{mv.name}/{mv.version}",
                        dst_path=str(tmp),
                        tracking_uri=registry_uri,
                    )
                else:
                    _download_files(mv, only, tmp, registry_uri)
            except MlflowException as e:
                raise store.RegistryUnreachable(
                    f"downloading {mv.name} version {mv.version} from {registry_uri} failed: {e}"
                ) from e
        write_version(tmp, mv, alias, describe(tmp, mv), registry_uri)
    return target


def _download_files(mv: Any, files: tuple[str, ...], folder: Path, registry_uri: str) -> None:
    """Download `files` of a model version into `folder`, each by itself: a logged model holds more
    than a client runs (environment files, input examples), and through a tracking server every file
    costs requests (22 for the whole of a force model, 12 for MLmodel and model.onnx). A file the
    version lacks is left out: `describe` then names it (a broken version, not an unreachable one)."""
    import mlflow
    from mlflow import MlflowClient
    from mlflow.exceptions import MlflowException

    root = MlflowClient(registry_uri, registry_uri).get_model_version_download_uri(mv.name, mv.version)
    for file in files:
        try:
            mlflow.artifacts.download_artifacts(
                artifact_uri=f"{root.rstrip('/')}/{file}", dst_path=str(folder), tracking_uri=registry_uri
            )
        except FileNotFoundError:
            pass
        except MlflowException as e:
            if e.error_code != "RESOURCE_DOES_NOT_EXIST":
                raise
