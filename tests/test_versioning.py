"""How raw batches are versioned: `dvc add` + git for the pointer, a DVC remote for the bytes.

Uses a local-directory remote, so it runs offline; an S3/GCS/SSH remote behaves the same way.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import yaml

from tests.helpers import tree_hash
from tests.projects import make_repo

REPO = Path(__file__).resolve().parents[1]
LAB_BATCH = REPO / "tests" / "fixtures" / "rig-log" / "lab-bench-a"
BATCH = "data/raw/lab-bench-a"


def run(root: Path, *cmd: str) -> str:
    """Run a command (git, or the venv's dvc) in `root`; fail with its output if it fails."""
    env = dict(os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}")
    done = subprocess.run(cmd, cwd=root, env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, f"{' '.join(cmd)} failed:\n{done.stdout}\n{done.stderr}"
    return done.stdout + done.stderr


def dir_md5(root: Path) -> str:
    """The directory hash (`<md5>.dir`) that `data/raw/lab-bench-a.dvc` records."""
    (out,) = yaml.safe_load((root / f"{BATCH}.dvc").read_text())["outs"]
    assert out["path"] == "lab-bench-a"
    return out["md5"]


def in_remote(remote: Path, md5: str) -> Path:
    """Where DVC 3 stores an object in a remote: files/md5/<first 2 hex>/<rest>."""
    return remote / "files" / "md5" / md5[:2] / md5[2:]


def test_a_raw_batch_is_versioned_pushed_restored_and_rolled_back(tmp_path):
    # Given a git + DVC project with a local-directory remote, and a lab batch dropped into data/raw
    work, remote = tmp_path / "work", tmp_path / "remote"
    make_repo(work)
    shutil.copytree(LAB_BATCH, work / BATCH)
    original = tree_hash(work / BATCH)
    run(work, "dvc", "remote", "add", "-d", "local", str(remote))

    # When the batch is added to DVC, its pointer committed to git and its bytes pushed
    run(work, "dvc", "add", BATCH)
    run(work, "git", "add", f"{BATCH}.dvc", "data/raw/.gitignore", ".dvc/config")
    run(work, "git", "commit", "-q", "-m", "raw: lab-bench-a")
    run(work, "dvc", "push")

    # Then git holds only the pointer (the folder itself is git-ignored) ...
    assert (work / "data" / "raw" / ".gitignore").read_text().split() == ["/lab-bench-a"]
    tracked = run(work, "git", "ls-files").split()
    assert f"{BATCH}.dvc" in tracked and not any(p.startswith(f"{BATCH}/") for p in tracked)
    # ... and the remote holds the folder's manifest (the .dvc file's md5) and every file's bytes
    first = dir_md5(work)
    assert first.endswith(".dir")
    manifest = json.loads(in_remote(remote, first).read_text())
    assert sorted(e["relpath"] for e in manifest) == sorted(original)
    for entry in manifest:
        stored = in_remote(remote, entry["md5"])
        assert stored.read_bytes() == (LAB_BATCH / entry["relpath"]).read_bytes()

    # When someone else clones the git repo (the remote is in the committed .dvc/config) and pulls
    clone = tmp_path / "clone"
    run(tmp_path, "git", "clone", "-q", str(work), str(clone))
    assert not (clone / BATCH).exists()
    run(clone, "dvc", "pull")
    # Then they get the batch back byte for byte
    assert tree_hash(clone / BATCH) == original

    # When the batch changes (a line appended) and is added and pushed again
    with (work / BATCH / "trials.csv").open("a") as f:
        f.write("t004,P2,45,0\n")
    run(work, "dvc", "add", BATCH)
    second = dir_md5(work)
    run(work, "git", "commit", "-q", "-am", "raw: lab-bench-a, one more trial")
    run(work, "dvc", "push")
    # Then the pointer's hash changed and both versions are in the remote
    assert second != first
    assert in_remote(remote, first).is_file() and in_remote(remote, second).is_file()
    assert tree_hash(work / BATCH) != original

    # When the previous commit's pointer is checked out and DVC checks the data out
    run(work, "git", "checkout", "HEAD~1", "--", f"{BATCH}.dvc")
    run(work, "dvc", "checkout", BATCH)
    # Then the old bytes are back, exactly
    assert dir_md5(work) == first
    assert tree_hash(work / BATCH) == original
