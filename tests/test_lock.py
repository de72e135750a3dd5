"""requirements.lock (what `make setup` installs) belongs to pyproject.toml: `make lock` was run after
the last change of a dependency (docs/reproducibility.md "Installing")."""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

REPO = Path(__file__).resolve().parents[1]


def locked() -> dict[str, str]:
    """{canonical name: pinned version} of requirements.lock."""
    pins = re.findall(r"^([A-Za-z0-9][A-Za-z0-9._-]*)==(\S+)", (REPO / "requirements.lock").read_text(), re.M)
    return {canonicalize_name(name): version for name, version in pins}


def test_every_dependency_and_extra_is_pinned_by_the_lock_within_its_bounds() -> None:
    # given: the project's dependencies and the extras make setup installs (dev, team), the client's
    # (client/pyproject.toml) among them
    pyproject = tomllib.loads((REPO / "pyproject.toml").read_text())
    project = pyproject["project"]
    wanted = [*project["dependencies"], *project["optional-dependencies"]["dev"]]
    wanted += project["optional-dependencies"]["team"]
    # the project's own distributions (the client, installed from its folder): their dependencies instead
    folders = {canonicalize_name(n): s["path"] for n, s in pyproject["tool"]["uv"]["sources"].items()}
    pins = locked()
    # when: each is looked up in the lock (markers for other platforms or Pythons aside)
    env = {"python_version": "3.11", "platform_python_implementation": "CPython", "sys_platform": "linux"}
    wrong = {}
    while wanted:
        req = Requirement(wanted.pop(0))
        if req.marker is not None and not req.marker.evaluate(env):
            continue
        if (folder := folders.get(canonicalize_name(req.name))) is not None:
            own = tomllib.loads((REPO / folder / "pyproject.toml").read_text())["project"]
            assert req.specifier.contains(own["version"]), f"{req}: {folder} is version {own['version']}"
            wanted += own["dependencies"] + [d for e in req.extras for d in own["optional-dependencies"][e]]
            continue
        pin = pins.get(canonicalize_name(req.name))
        if pin is None or not req.specifier.contains(pin, prereleases=True):
            wrong[str(req)] = pin
    # then: every one is pinned, inside the bounds pyproject.toml gives it
    assert wrong == {}


def test_the_lock_pins_the_cpu_build_of_torch_with_hashes_only() -> None:
    # given: the lock's text
    text = (REPO / "requirements.lock").read_text()
    # then: torch is the CPU build, every pin has a hash, and no machine's path is in it
    assert locked()["torch"].endswith("+cpu")
    blocks = re.split(r"\n(?=[A-Za-z0-9])", text.split("\n", 2)[2])
    assert [b.split()[0] for b in blocks if b.strip() and "--hash=sha256:" not in b] == []
    assert "/opt/" not in text and "file://" not in text
