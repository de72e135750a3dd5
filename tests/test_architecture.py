"""The layout's rules: stages are entry points nothing imports; the simulator's client (client/, its own
distribution) imports none of the training code (tests/client/test_imports.py and test_light_install.py
run it); dvc.yaml lists the code each stage runs, package by package."""

from __future__ import annotations

import subprocess
import sys

import yaml

from tests.architecture import (
    CLIENT,
    PACKAGE,
    REPO,
    ROOTS,
    RUNTIME,
    closure,
    imported_modules,
    listed_code_deps,
    module_file,
    module_name,
    package_files,
    stage_deps,
    stage_modules,
)


def test_nothing_in_the_package_or_the_benchmarks_imports_a_stage() -> None:
    # given: every module of the package and every benchmark script (the stage tests under
    # tests/stages/ are the one place that loads a stage: they drive its command line)
    files = [*REPO.joinpath(PACKAGE).rglob("*.py"), *REPO.joinpath("benchmarks").glob("*.py")]
    # when: reading their imports
    offenders = {
        module_name(f) if f.is_relative_to(REPO / PACKAGE) else f.name: sorted(
            m for m in imported_modules(f) if m.startswith(f"{PACKAGE}.stages")
        )
        for f in files
    }
    # then: no stage module is imported anywhere
    assert {k: v for k, v in offenders.items() if v} == {}


def test_every_stage_module_is_run_by_dvc_and_is_thin() -> None:
    # given: the stage modules on disk and the ones dvc.yaml runs
    on_disk = {p for p in REPO.joinpath(PACKAGE, "stages").glob("*.py") if p.name != "__init__.py"}
    # then: each is a stage of dvc.yaml, and each stays an entry point (about 150 lines at most)
    assert on_disk == set(stage_modules().values())
    assert {p.name: n for p in on_disk if (n := len(p.read_text().splitlines())) > 150} == {}


def test_the_client_distribution_imports_nothing_of_the_training_package() -> None:
    # given: every module of the client's distribution (client/: the client and the runtime it shares)
    files = [*package_files(CLIENT), *package_files(RUNTIME)]
    # when: reading the project modules each names in an import (function-local imports too)
    offenders = {
        module_name(f): sorted(m for m in imported_modules(f) if m.split(".")[0] == PACKAGE) for f in files
    }
    # then: none names the training package: `pip install ./client` gives all the client runs
    assert {k: v for k, v in offenders.items() if v} == {}


def test_the_runtime_imports_nothing_of_the_client() -> None:
    # given: the runtime, which the training package imports as well
    files = package_files(RUNTIME)
    # then: it names no module of the client (data flows one way: runtime <- client, runtime <- pipeline)
    offenders = {
        module_name(f): sorted(m for m in imported_modules(f) if m.split(".")[0] == CLIENT) for f in files
    }
    assert {k: v for k, v in offenders.items() if v} == {}


def test_the_client_loads_only_the_client_and_the_runtime() -> None:
    # given: the project files the client can load, by static reading, from its package on
    loaded = {module_name(p) for p in closure(ROOTS[CLIENT] / CLIENT / "__init__.py")}
    # then: each belongs to one of the client distribution's two packages
    assert sorted(m for m in loaded if m.split(".")[0] not in (CLIENT, RUNTIME)) == []


def test_dvc_yaml_lists_the_code_each_stage_imports_package_by_package() -> None:
    # given: dvc.yaml's stages and, for each, the project files its module can load
    stages = yaml.safe_load((REPO / "dvc.yaml").read_text())["stages"]
    # when: comparing them, grouped by package, with the code deps dvc.yaml lists
    wrong = {
        name: {"expected": stage_deps(path), "listed": listed_code_deps(stages[name])}
        for name, path in stage_modules().items()
    }
    # then: each stage lists every package it loads anything from and no other, and the top-level
    # and stage modules it loads as files (`python -m tests.architecture --write` puts them there)
    assert {k: v for k, v in wrong.items() if v["expected"] != v["listed"]} == {}


def test_a_package_folder_in_dvc_yaml_is_hashed_without_its_bytecode() -> None:
    # given: a compiled module's bytecode beside the sources of a package dvc.yaml lists as a folder
    cache = REPO / "pipeline" / "modelling" / "__pycache__"
    # when: asking DVC whether it reads that bytecode as part of the folder
    found = subprocess.run(
        [sys.executable, "-m", "dvc", "check-ignore", str((cache / "fit.cpython-311.pyc").relative_to(REPO))],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
    )
    # then: it is ignored (.dvcignore), so running Python does not change the folder's hash
    assert found.returncode == 0, found.stdout + found.stderr


def test_no_file_dvc_yaml_lists_as_a_dependency_is_empty() -> None:
    # given: every code file dvc.yaml lists as a stage dependency (folders are hashed as a whole)
    stages = yaml.safe_load((REPO / "dvc.yaml").read_text())["stages"]
    files = {REPO / d for s in stages.values() for d in listed_code_deps(s) if (REPO / d).is_file()}
    # when: looking for empty ones
    empty = sorted(str(f.relative_to(REPO)) for f in files if f.stat().st_size == 0)
    # then: there are none: DVC warns "'<file>' is empty" for each, in every stage of every run
    assert empty == []


def test_the_live_session_imports_no_training_module() -> None:
    # given: what `needlecue live` loads to run a session (the emulator, a test tool, reads rig logs)
    loaded = {module_name(p) for p in closure(REPO / PACKAGE / "live" / "app.py")}
    # then: the client's side only, as on a simulator
    training = ("pipeline.modelling", "pipeline.metrics", "pipeline.reporting", "pipeline.stages")
    training += ("pipeline.rig", "pipeline.signals", "pipeline.sim", "pipeline.dataset")
    assert sorted(m for m in loaded if m.startswith(training)) == []


def test_the_package_import_graph_has_no_cycle() -> None:
    # given: every module of the project's three packages and the project modules each one names in an
    # import (at the top or inside a function: a lazy import hides a loop from Python, not from a reader)
    import networkx as nx

    graph = nx.DiGraph()
    for f in [*package_files(PACKAGE), *package_files(CLIENT), *package_files(RUNTIME)]:
        for module in imported_modules(f):
            target = module_file(module)
            if target is not None and target != f:
                graph.add_edge(module_name(f), module_name(target))
    # then: no module reaches itself
    assert list(nx.simple_cycles(graph)) == []


def test_an_edit_to_the_rig_format_or_ingest_reruns_no_model_stage() -> None:
    # given: the code deps of every stage from choose on (what trains, calibrates, predicts, scores)
    modules = stage_modules()
    downstream = ("choose", "train", "calibrate", "predict", "cues", "needs", "evaluate", "register")
    # then: none of them loads anything from pipeline/rig (the front end they share is the runtime's,
    # client/needlecue_runtime/frontend.py)
    assert {s: d for s in downstream if "pipeline/rig" in (d := stage_deps(modules[s]))} == {}
