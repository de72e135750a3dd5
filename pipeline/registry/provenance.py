"""The exact data behind a registered version: its run keeps the project's `dvc.lock` as it was when the
version was tracked (artifact `dvc/dvc.lock`), and the version's tags say the git commit and that
file's sha256. `restore_lock` puts that dvc.lock into a clone checked out at the commit; `dvc pull`
then brings every output it names from the DVC remote, byte for byte.
"""

from __future__ import annotations

import hashlib
import shutil
import subprocess
import tempfile
from pathlib import Path
from typing import Any

from needlecue_runtime.registry.mlflow_env import patience
from needlecue_runtime.registry.store import TAG, connect, model_name, tracking_uri
from pipeline.registry.tracking import LOCK_ARTIFACT


class ProvenanceError(RuntimeError):
    """The version cannot be traced to its data here (no record, another commit checked out, ...)."""


def version_provenance(angle_deg: float, version: int, uri: str | None = None) -> dict[str, Any]:
    """{model, version, run_id, git_commit, dvc_lock_sha256} of `needle-force-<angle>` version `version`."""
    with patience():
        mv = connect(uri, must_exist=True).get_model_version(model_name(angle_deg), str(version))
    name = model_name(angle_deg)
    tags = mv.tags or {}
    if f"{TAG}dvc_lock_sha256" not in tags:
        raise ProvenanceError(f"{name} v{version}: registered without a dvc.lock record (an older needlecue)")
    return {
        "model": name,
        "version": int(version),
        "run_id": mv.run_id,
        "git_commit": tags.get("git_commit", "unknown"),
        "dvc_lock_sha256": tags[f"{TAG}dvc_lock_sha256"],
    }


def head_commit(root: Path) -> str:
    done = subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True)
    if done.returncode != 0:
        raise ProvenanceError(f"{root} is not a git clone: {done.stderr.strip()}")
    return done.stdout.strip()


def restore_lock(angle_deg: float, version: int, root: Path, uri: str | None = None) -> dict[str, Any]:
    """Write the version's dvc.lock into `root` (a clone at the version's commit), checked against the
    sha256 its tags record; returns the provenance. Refuses if another commit is checked out: the
    code and dvc.yaml must be the ones that made it."""
    import mlflow

    found = version_provenance(angle_deg, version, uri)
    commit = found["git_commit"].removesuffix("+dirty")
    head = head_commit(root)
    if commit != head:
        raise ProvenanceError(
            f"{found['model']} v{version} was made at commit {found['git_commit']}; {root} is at {head}: "
            f"`git checkout {commit}` first"
        )
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(
            mlflow.artifacts.download_artifacts(
                run_id=found["run_id"],
                artifact_path=LOCK_ARTIFACT,
                dst_path=tmp,
                tracking_uri=uri or tracking_uri(),
            )
        )
        digest = hashlib.sha256(path.read_bytes()).hexdigest()
        if digest != found["dvc_lock_sha256"]:
            raise ProvenanceError(
                f"the run's dvc.lock has sha256 {digest}, the version's tag says {found['dvc_lock_sha256']}"
            )
        shutil.copyfile(path, root / "dvc.lock")
    return found
