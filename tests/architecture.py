"""The package's import graph, read statically (every `import`, at the top or inside a function):
which project files a module can load, and so which code each dvc.yaml stage depends on.
`python -m tests.architecture` prints, per stage, the code deps dvc.yaml must list;
`python -m tests.architecture --write` puts them into dvc.yaml."""

from __future__ import annotations

import ast
import re
import sys
from functools import cache
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]
PACKAGE = "pipeline"  # the training package
CLIENT = "needlecue_client"  # the simulator's client (client/, its own distribution)
RUNTIME = "needlecue_runtime"  # what the client and training share (client/ as well)
# each import package of the project and the folder that holds it
ROOTS = {PACKAGE: REPO, CLIENT: REPO / "client", RUNTIME: REPO / "client"}
# each package's folder as dvc.yaml names it (pipeline, client/needlecue_runtime, ...)
FOLDERS = tuple((root / package).relative_to(REPO).as_posix() for package, root in ROOTS.items())


def package_files(package: str) -> list[Path]:
    """Every module of one of the project's import packages."""
    return sorted(ROOTS[package].joinpath(package).rglob("*.py"))


def module_file(module: str) -> Path | None:
    """The file of a project module (`pipeline.cues.packs` -> pipeline/cues/packs.py,
    `needlecue_runtime.cues.pack` -> client/needlecue_runtime/cues/pack.py), None if not ours."""
    parts = module.split(".")
    if parts[0] not in ROOTS:
        return None
    base = ROOTS[parts[0]].joinpath(*parts)
    for candidate in (base.with_suffix(".py"), base / "__init__.py"):
        if candidate.is_file():
            return candidate
    return None


def module_name(path: Path) -> str:
    root = next(r for package, r in ROOTS.items() if path.is_relative_to(r / package))
    rel = path.relative_to(root).with_suffix("")
    parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
    return ".".join(parts)


def imported_modules(path: Path) -> set[str]:
    """Every module named by an import statement in `path` (absolute names; `from a import b` gives
    both `a` and `a.b`, since b may be a module)."""
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            out.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.add(node.module)
            out.update(f"{node.module}.{alias.name}" for alias in node.names)
    return out


@cache
def project_imports(path: Path) -> frozenset[Path]:
    """The project files `path` imports directly, with the `__init__.py` of every package on the way
    (importing `a.b.c` runs `a/__init__.py` and `a/b/__init__.py`)."""
    out: set[Path] = set()
    for module in imported_modules(path):
        parts = module.split(".")
        for i in range(1, len(parts) + 1):
            found = module_file(".".join(parts[:i]))
            if found is not None:
                out.add(found)
    return frozenset(out - {path})


def closure(path: Path) -> set[Path]:
    """`path` and every project file it can load, transitively."""
    seen: set[Path] = set()
    todo = [path]
    while todo:
        p = todo.pop()
        if p in seen:
            continue
        seen.add(p)
        todo.extend(project_imports(p))
    return seen


LAUNCHER = f"{PACKAGE}.execution.run"


def stage_modules() -> dict[str, Path]:
    """{dvc.yaml stage name: the file of the stage module its cmd runs
    (`python -m pipeline.execution.run STAGE`)}."""
    stages = yaml.safe_load((REPO / "dvc.yaml").read_text())["stages"]
    out = {}
    for name, stage in stages.items():
        match = re.match(rf"python -m {re.escape(LAUNCHER)} (\w+)", stage["cmd"])
        if match is None:
            raise ValueError(f"dvc.yaml stage {name!r}: cmd does not run `python -m {LAUNCHER} STAGE`")
        found = module_file(f"{PACKAGE}.stages.{match.group(1)}")
        if found is None:
            raise ValueError(f"dvc.yaml stage {name!r}: no stage module {match.group(1)}")
        out[name] = found
    return out


def _process_files(module_file_: Path) -> set[Path]:
    """The project files `python -m MODULE` can load: the packages' `__init__.py` on the way, then
    the module and its imports."""
    parts = module_name(module_file_).split(".")
    inits = [module_file(".".join(parts[:i])) for i in range(1, len(parts))]
    return set().union(*(closure(p) for p in [*inits, module_file_] if p is not None))


def code_deps(stage_file: Path) -> list[str]:
    """The project files a stage's processes can load, as dvc.yaml lists them (sorted, repo-relative):
    the launcher's, then the stage module's it execs."""
    launcher = module_file(LAUNCHER)
    assert launcher is not None
    files = _process_files(launcher) | _process_files(stage_file)
    return sorted(p.relative_to(REPO).as_posix() for p in files)


def stage_deps(stage_file: Path) -> list[str]:
    """The code deps dvc.yaml lists for a stage, grouped by package: each library package the stage
    loads anything from as its folder (`pipeline/modelling`, subpackages included), the top-level
    modules and the stage's own module as files. The folders first, then the files, each sorted."""
    out = set()
    for dep in code_deps(stage_file):
        top = next(folder for folder in FOLDERS if dep.startswith(f"{folder}/"))  # the package's folder
        inner = dep[len(top) + 1 :].split("/")
        library = len(inner) > 1 and inner[0] != "stages"
        out.add(f"{top}/{inner[0]}" if library else dep)
    return sorted(out, key=lambda dep: (dep.endswith(".py"), dep))


def listed_code_deps(stage: dict) -> list[str]:
    """The deps of a dvc.yaml stage that are project code (files and package folders)."""
    return [d for d in stage.get("deps", []) if str(d).startswith(tuple(f"{f}/" for f in FOLDERS))]


# one code dep of a stage, as dvc.yaml writes it
CODE_DEP = re.compile(rf"^      - ({'|'.join(map(re.escape, FOLDERS))})/\S*$")
STAGE = re.compile(r"^  (\w+):\s*$")


def write_dvc_yaml(path: Path) -> None:
    """Replace each stage's run of code deps in dvc.yaml by `stage_deps` (everything else kept)."""
    modules = stage_modules()
    lines, out, stage = path.read_text().split("\n"), [], None
    i = 0
    while i < len(lines):
        if match := STAGE.match(lines[i]):
            stage = match.group(1)
        if stage in modules and CODE_DEP.match(lines[i]):
            while i < len(lines) and CODE_DEP.match(lines[i]):
                i += 1
            out += [f"      - {dep}" for dep in stage_deps(modules[stage])]
            continue
        out.append(lines[i])
        i += 1
    path.write_text("\n".join(out))


def main() -> None:
    if sys.argv[1:] == ["--write"]:
        write_dvc_yaml(REPO / "dvc.yaml")
        return
    for name, path in stage_modules().items():
        print(f"{name}:")
        for dep in stage_deps(path):
            print(f"  - {dep}")


if __name__ == "__main__":
    sys.exit(main())
