"""`python -m pipeline.execution.run STAGE`: the numeric libraries pinned, so every machine writes the same
bytes; proven here by emulating other machines' instruction sets on this one (tests/machines.py)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from pipeline.execution import run as launcher
from tests.machines import LEVELS, switchable_levels
from tests.projects import copy_project, make_tiny_project, run

REPO = Path(__file__).resolve().parents[1]
# the data stages, a small training of every model, predictions on both cores and the cue scoring
TARGETS = ("cues",)


def test_pinned_env_keeps_a_machines_own_masks_and_adds_ours() -> None:
    # given: an environment that already masks a feature and enables one in numpy
    env = {
        "NPY_DISABLE_CPU_FEATURES": "AVX512_SPR,X86_V4",
        "NPY_ENABLE_CPU_FEATURES": "X86_V3",
        "GLIBC_TUNABLES": "glibc.malloc.check=3:glibc.cpu.hwcaps=-AVX512F",
        "ATEN_CPU_CAPABILITY": "avx512",
        "HOME": "/home/x",
    }
    # when: it is pinned
    pinned = launcher.pinned_env(env)
    # then: every dispatch target is off once, the machine's own masks stay, other tunables stay
    assert pinned["NPY_DISABLE_CPU_FEATURES"].split() == ["AVX512_SPR", "X86_V4", "X86_V3", "AVX512_ICL"]
    assert "NPY_ENABLE_CPU_FEATURES" not in pinned  # numpy refuses to start with both naming a feature
    tunables = pinned["GLIBC_TUNABLES"].split(":")
    assert tunables[0] == "glibc.malloc.check=3"
    masks = tunables[1].removeprefix("glibc.cpu.hwcaps=").split(",")
    assert masks[0] == "-AVX512F" and {"-AVX2", "-FMA"} <= set(masks) and len(masks) == len(set(masks))
    assert pinned["ATEN_CPU_CAPABILITY"] == "default" and pinned["HOME"] == "/home/x"


def test_the_pin_names_every_numpy_dispatch_target() -> None:
    # given: the targets this numpy can dispatch to at run time
    from numpy._core._multiarray_umath import __cpu_dispatch__

    # then: the launcher turns off each of them (a numpy with a new target fails here, loudly)
    assert set(__cpu_dispatch__) <= set(launcher.NUMPY_DISPATCH)


def test_a_process_started_with_the_pinned_env_runs_the_baseline_paths() -> None:
    # given: a python started as the launcher starts a stage
    probe = (
        "import json, numpy, torch, threadpoolctl\n"
        "from numpy._core._multiarray_umath import __cpu_features__ as f\n"
        "blas = [i for i in threadpoolctl.threadpool_info() if i['internal_api'] == 'openblas']\n"
        "print(json.dumps({'v3': f['X86_V3'], 'torch': torch.backends.cpu.get_cpu_capability(),\n"
        "  'blas': sorted({(i['architecture'], i['num_threads']) for i in blas})}))"
    )
    env = launcher.pinned_env(os.environ)
    # when: it reports what its libraries chose
    out = subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True, text=True, check=True)
    seen = json.loads(out.stdout)
    # then: numpy's AVX2 paths are off, torch runs its default kernels, OpenBLAS is Nehalem on 1 thread
    assert seen["v3"] is False
    assert seen["torch"] == "DEFAULT"
    assert seen["blas"] == [["Nehalem", 1]]


def test_an_unknown_stage_is_refused_with_the_list_of_stages() -> None:
    # when: the launcher is asked for a stage that does not exist
    cmd = [sys.executable, "-m", "pipeline.execution.run", "trian"]
    done = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True)
    # then: it says which ones exist, and runs nothing
    assert done.returncode == 1
    assert "STAGE is one of:" in done.stderr and "train" in done.stderr


def out_hashes(root: Path) -> dict[str, str]:
    """{stage/out path: md5} from dvc.lock: equal iff the stages wrote the same bytes."""
    lock = yaml.safe_load((root / "dvc.lock").read_text())["stages"]
    return {f"{name}/{o['path']}": o["md5"] for name, stage in lock.items() for o in stage.get("outs", [])}


def repro_as(root: Path, level: str, targets: tuple[str, ...] = TARGETS) -> dict[str, str]:
    """`dvc repro` of `targets` on the emulated `level`, the stages that can use worker processes
    using them however small the data."""
    run(root, "dvc", "repro", *targets, env={**LEVELS[level], "NEEDLECUE_WORKERS": "2"})
    return out_hashes(root)


def differing(hashes: dict[str, dict[str, str]]) -> dict[str, list[str]]:
    """{machine: the outs whose bytes differ from the first machine's}, for those that differ (the outs
    the first machine wrote: another may have run more stages)."""
    first = next(iter(hashes.values()))
    differ = {m: sorted(k for k in first if h.get(k) != first[k]) for m, h in hashes.items()}
    return {m: outs for m, outs in differ.items() if outs}


@pytest.mark.slow
def test_every_emulated_machine_writes_the_same_bytes(tiny_built: Path, tmp_path: Path) -> None:
    # given: the small project built on this machine as it is (its own, highest, level, with no worker
    # processes: the shared build, tests/conftest.py, uses them only where the work repays them, never
    # at this size), and the lowest instruction-set level it can switch to, with worker processes: one
    # build that differs from this machine's both ways a machine can (a level between the two takes
    # neither extreme's paths, but the pin puts every level on the baseline paths:
    # test_a_process_started_with_the_pinned_env_runs_the_baseline_paths)
    lowest = switchable_levels()[0]
    machine = f"{lowest} with worker processes"
    # when: the data stages, a small training, the predictions and the cues run there, as dvc.yaml
    # runs them
    hashes = {
        machine: repro_as(make_tiny_project(tmp_path / "emulated")[0], lowest),
        "this machine": out_hashes(tiny_built),
    }
    # then: every output is byte-identical
    stages = {out.split("/")[0] for out in hashes[machine]}
    assert {"simulate", "ingest", "resample", "split", "predict", "cues"} <= stages
    assert len([s for s in stages if s.startswith("train@")]) == 6  # 2 angles x 3 models
    assert differing(hashes) == {}, f"{machine} against this one"


@pytest.mark.slow
def test_without_the_pin_the_emulated_machines_differ(tiny_built: Path, tmp_path: Path) -> None:
    # given: the lowest and highest levels this machine can switch to, each with a copy of the small
    # project built here, its stages run unpinned
    levels = switchable_levels()
    if len(levels) < 2:
        pytest.skip(f"this machine can switch to {levels} only: nothing to compare")
    hashes = {}
    for level in (levels[0], levels[-1]):
        root = copy_project(tiny_built, tmp_path / level)[0]
        dvc_yaml = root / "dvc.yaml"
        unpinned = dvc_yaml.read_text().replace(
            "python -m pipeline.execution.run ", "python -m pipeline.stages."
        )
        dvc_yaml.write_text(unpinned)
        # when: one network's training runs again on each (the data it reads: the build's own)
        run(root, "dvc", "repro", "--single-item", "--force", "train@15-fnn", env=LEVELS[level])
        hashes[level] = out_hashes(root)
    # then: its outputs differ, so the emulation reaches code paths that the pin has to hold still
    assert differing(hashes), "the emulated levels gave the same bytes even without the pin"
