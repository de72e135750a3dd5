"""Throw-away copies of the project for end-to-end tests: code, dvc.yaml and params on a small
simulated rig, with their own DVC repo; `run` drives dvc or python in one."""

from __future__ import annotations

import contextlib
import os
import shutil
import sqlite3
import subprocess
import sys
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import pandas as pd
import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]
LAB_BATCH = REPO / "tests" / "fixtures" / "rig-log" / "lab-bench-a"
SMALL_SIM = {
    "angles_deg": [15, 45],
    "train_batches": 1,
    "trials_per_angle": 2,  # x 2 units: 4 training trials per angle
    "heldout_trials_per_angle": 2,
    "calibration_trials_per_angle": 1,
    "units": ["est-sim-001", "est-sim-002"],
    "new_units": ["est-sim-101"],
}
# three training units and a new one with a calibration batch (the unit swap and any-rig tests)
A, B, C, D = "unit-a", "unit-b", "unit-c", "unit-d"
SWAP_SIM = {
    "angles_deg": [15, 45],
    "train_batches": 1,
    "trials_per_angle": 2,  # x 3 units: 6 training trials per angle
    "heldout_trials_per_angle": 2,
    "calibration_trials_per_angle": 1,
    "units": [A, B, C],
    "new_units": [D],
}
TINY_MODELS = {
    "fnn": {"max_epochs": 3, "patience": 2},
    "lstm": {"max_epochs": 2, "patience": 1},
}


# what a copy of the code leaves out: bytecode, and what building or installing the client leaves behind
COPY_IGNORE = shutil.ignore_patterns("__pycache__", "build", "*.egg-info")


def make_project(root: Path, simulate: dict) -> Path:
    """A throw-away copy of the project (code, dvc.yaml, params.yaml) with its own DVC repo."""
    root.mkdir()
    for name in ("dvc.yaml", ".dvcignore"):
        if (REPO / name).exists():
            shutil.copy(REPO / name, root / name)
    for package in ("pipeline", "client"):  # the training package; the client's and the runtime's
        shutil.copytree(REPO / package, root / package, ignore=COPY_IGNORE)
    params = yaml.safe_load((REPO / "params.yaml").read_text())
    params["simulate"].update(simulate)
    if "angles_deg" in simulate:  # train only the angles the small rig records
        params["train"]["angles"] = simulate["angles_deg"]
    (root / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    (root / "data" / "raw").mkdir(parents=True)
    run(root, "dvc", "init", "--no-scm", "-q")  # DVC's analytics: off for the suite (pyproject.toml)
    return root


def run(root: Path, *cmd: str, env: Mapping[str, str] | None = None) -> str:
    """Run a command of the venv (dvc, python) in the copy, with `env` added to the environment;
    fail with its output if it fails. The copy's own client/ comes first on the import path (the
    venv's editable install points at the checkout's), as the pipeline's own code does from the cwd."""
    path = f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"
    full = dict(os.environ, **(env or {}), PATH=path, PYTHONPATH=str(root / "client"))
    done = subprocess.run(cmd, cwd=root, env=full, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, f"{' '.join(cmd)} failed:\n{done.stdout}\n{done.stderr}"
    return done.stdout + done.stderr


def use_small_models(root: Path, kinds: tuple[str, ...] = ("ls", "fnn")) -> dict:
    """Train, cue and register only `kinds`, with few-epoch networks (end-to-end tests of the plumbing,
    not of accuracy); returns the params written."""
    params = yaml.safe_load((root / "params.yaml").read_text())
    params["train"]["kinds"] = list(kinds)
    params["cues"]["kinds"] = params["register"]["candidates"] = list(kinds)
    for model, update in TINY_MODELS.items():
        params[model].update(update)
    (root / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    return params


def make_tiny_project(root: Path) -> tuple[Path, dict]:
    """make_project on the small rig with few-epoch networks (for tests of the DAG, not of accuracy);
    returns the folder and its params."""
    root = make_project(root, SMALL_SIM)
    params = yaml.safe_load((root / "params.yaml").read_text())
    for model, update in TINY_MODELS.items():
        params[model].update(update)
    (root / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    return root, params


def build_tiny_project(root: Path) -> Path:
    """make_tiny_project reproduced through every stage but register (which needs a test's own MLflow
    store): what several end-to-end tests start from. Copy it with `copy_project`."""
    make_tiny_project(root)
    # on both cores, as `make repro` runs it: the test that every machine writes the same bytes
    # compares this build with plain `dvc repro`s of the same project
    run(root, sys.executable, "-m", "pipeline.cli", "repro", *built_stages(root))
    return root


def built_stages(root: Path) -> list[str]:
    """The stages `build_tiny_project` runs: all but register."""
    return [s for s in run(root, "dvc", "stage", "list", "--name-only").split() if s != "register"]


@dataclass(frozen=True)
class Registered:
    """A reproduced project with register run too (`project`), and the MLflow store it registered into
    (`store`, a folder): the `tiny_registered` fixture; a test takes a copy with `copy_registered`."""

    project: Path
    store: Path


def copy_registered(registered: Registered, to: Path, monkeypatch: pytest.MonkeyPatch) -> tuple[Path, dict]:
    """A copy of the registered project at `to`/proj and of its store at `to`/store, which MLflow's
    environment (MLFLOW_TRACKING_URI and MLFLOW_REGISTRY_URI) names for the rest of the test.
    Returns the project's folder and its params."""
    uri = copy_store(registered.store, to / "store")
    for key in ("MLFLOW_TRACKING_URI", "MLFLOW_REGISTRY_URI"):
        monkeypatch.setenv(key, uri)
    return copy_project(registered.project, to / "proj")


def store_uri(store: Path) -> str:
    """The MLflow tracking URI of the sqlite store in folder `store` (its artifacts beside it)."""
    return f"sqlite:///{store / 'mlflow.db'}"


def register_into(root: Path, store: Path) -> None:
    """`dvc repro` of a copy of the tiny build, into a new MLflow store in folder `store` (MLflow makes
    its tables: no `new_store` here, so one end-to-end run does that). It fails unless the one stage it
    runs is register: the build's dvc.lock (`needlecue repro`'s, a stage at a time) leaves every other
    stage up to date for plain `dvc repro`."""
    store.mkdir()
    uri = store_uri(store)
    out = run(root, "dvc", "repro", env={"MLFLOW_TRACKING_URI": uri, "MLFLOW_REGISTRY_URI": uri})
    assert reran_stages(out) == {"register"}, out


def reran_stages(dvc_output: str) -> set[str]:
    """The stages `dvc repro` ran, from what it printed."""
    return {line.split("'")[1] for line in dvc_output.splitlines() if line.startswith("Running stage")}


def make_empty_store(folder: Path) -> None:
    """An MLflow sqlite store in `folder` (new) with its tables made and nothing in them: what
    `new_store` copies. Made with `folder` as the working directory, where MLflow puts the default
    experiment's artifacts (`./mlruns`), so that a copy moves them with it."""
    from mlflow import MlflowClient

    folder.mkdir()
    with contextlib.chdir(folder):
        MlflowClient(store_uri(folder)).search_experiments()


def new_store(empty: Path, folder: Path) -> str:
    """A new MLflow store in `folder` (made if missing), a copy of the empty store in folder `empty`
    (`make_empty_store`, the `empty_store` fixture): MLflow makes a store's tables by running its
    migrations, about 1.5 s a store, which the suite would pay some 60 times. Returns its URI."""
    folder.mkdir(parents=True, exist_ok=True)
    shutil.copy(empty / "mlflow.db", folder / "mlflow.db")
    _move_paths(folder / "mlflow.db", empty, folder)
    return store_uri(folder)


def copy_store(store: Path, to: Path) -> str:
    """A copy of the MLflow store in folder `store` at `to`; returns its URI."""
    shutil.copytree(store, to)
    _move_paths(to / "mlflow.db", store, to)
    return store_uri(to)


def _move_paths(path: Path, store: Path, to: Path) -> None:
    """MLflow keeps absolute paths in its sqlite file `path` (where each experiment's, run's and
    version's artifacts are): every one under folder `store` is moved to folder `to`."""
    old, new = str(store), str(to)
    with sqlite3.connect(path) as db:
        tables = [t for (t,) in db.execute("SELECT name FROM sqlite_master WHERE type = 'table'")]
        for table in tables:
            for _, column, kind, *_ in db.execute(f'PRAGMA table_info("{table}")').fetchall():
                if any(word in kind.upper() for word in ("CHAR", "TEXT", "CLOB")):
                    db.execute(
                        f'UPDATE "{table}" SET "{column}" = replace("{column}", ?, ?) '
                        f'WHERE instr("{column}", ?) > 0',
                        (old, new, old),
                    )
    db.close()


def copy_project(built: Path, root: Path) -> tuple[Path, dict]:
    """A copy of a reproduced project (its DVC cache included, its DVC state not: that is per folder)
    at `root`; `dvc repro` there runs only what the copy lacks. Returns the folder and its params."""
    state = lambda folder, _names: ["tmp"] if folder.endswith(".dvc") else []  # noqa: E731
    shutil.copytree(built, root, symlinks=True, ignore=state)
    return root, yaml.safe_load((root / "params.yaml").read_text())


def first_external_trial(root: Path, angle: str, unit: str) -> pd.DataFrame:
    """The rows of `unit`'s first external trial at `angle`, in time order (index: the rows'
    positions in the split file, as the predictions store keeps them)."""
    external = pd.read_parquet(root / "data" / "processed" / angle / "external.parquet")
    trial = external[external.unit_id == unit]
    first = trial[["batch_id", "trial_id"]].drop_duplicates().iloc[0]
    return trial[(trial.batch_id == first.batch_id) & (trial.trial_id == first.trial_id)].sort_values("t_s")


def make_repo(root: Path) -> None:
    """An empty git + DVC project at `root` (new), its DVC config committed."""
    root.mkdir()
    run(root, "git", "init", "-q")
    for key, value in (("user.name", "needlecue test"), ("user.email", "test@example.invalid")):
        run(root, "git", "config", key, value)
    run(root, "git", "config", "commit.gpgsign", "false")
    run(root, "dvc", "init", "-q")
    run(root, "git", "add", "-A")
    run(root, "git", "commit", "-q", "-m", "dvc init")
