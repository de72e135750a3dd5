"""The committed dvc.lock belongs to the committed code and params: no stage's code or params changed
since the lock was written. (That the lock's outputs are what this machine computes is `make verify`:
the whole pipeline, too long for every test run; docs/reproducibility.md.)"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def stale_inputs(status: dict) -> dict[str, dict]:
    """Per stage, the inputs `dvc status --json` finds changed, except those only missing: in a clone
    without the pipeline's outputs every generated input is "deleted", which says nothing of the lock."""
    stale: dict[str, dict] = {}
    for stage, changes in status.items():
        for change in changes:
            deps = change.get("changed deps", {}) if isinstance(change, dict) else {}
            changed = {path: how for path, how in deps.items() if how != "deleted"}
            if changed:
                stale.setdefault(stage, {}).update(changed)
    return stale


def test_stale_inputs_keeps_changed_code_and_params_and_drops_missing_outputs() -> None:
    # Given dvc's status of a clone whose upstream outputs are missing, one file and one param changed
    status = {
        "ingest": [{"changed deps": {"data/simulated": "deleted"}}, {"changed outs": {"x": "not in cache"}}],
        "resample": [{"changed deps": {"pipeline/signals/resample.py": "modified"}}],
        "simulate": [{"changed deps": {"params.yaml": {"simulate": "modified"}}}],
    }
    # Then only the code and the params are stale
    assert stale_inputs(status) == {
        "resample": {"pipeline/signals/resample.py": "modified"},
        "simulate": {"params.yaml": {"simulate": "modified"}},
    }


def test_the_committed_dvc_lock_matches_the_code_and_params_of_every_stage() -> None:
    # Given this checkout (with or without the pipeline's outputs)
    dvc = Path(sys.executable).parent / "dvc"
    # When DVC compares each stage's code and params with dvc.lock
    done = subprocess.run(
        [str(dvc), "status", "--json"], cwd=REPO, capture_output=True, text=True, timeout=300
    )
    assert done.returncode == 0, done.stderr
    # Then nothing a stage reads from git changed since the lock was written
    stale = stale_inputs(json.loads(done.stdout or "{}"))
    assert not stale, (
        f"dvc.lock is older than these stages' code or params: {stale}. Run `make verify` (the pipeline, "
        "then the check) and commit the dvc.lock and reports/metrics.json it writes"
    )


def test_dvc_parses_its_yaml_with_the_c_parser() -> None:
    # given: the loader DVC builds to read dvc.yaml, dvc.lock and params.yaml (dvc.utils.serialize:
    # ruamel's YAML of the "safe" type)
    from ruamel.yaml import YAML

    # then: it is ruamel's C parser (pyproject: ruamel.yaml.clib), not the pure-Python one that made a
    # `dvc repro` with nothing to do a third slower
    assert YAML(typ="safe").Parser.__name__ == "CParser"
