"""Fixtures of the deployed model's tests: a champion on rest-relative volts, registered with a unit
calibrated with it on its FSRs' conductance, and a held-out trial of that unit; and the same of a model
of fz alone (a load cell's reference)."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.deploy.builders import Champion, registered_champion
from tests.projects import new_store


@pytest.fixture(scope="package")
def champion(empty_store: Path, tmp_path_factory: pytest.TempPathFactory) -> Champion:
    """Registered once for the package's tests, in a store of its own."""
    root = tmp_path_factory.mktemp("deployed")
    return registered_champion(new_store(empty_store, root), root)


@pytest.fixture(scope="package")
def fz_champion(empty_store: Path, tmp_path_factory: pytest.TempPathFactory) -> Champion:
    """The champion of a lab whose reference recorded fz alone, in a store of its own."""
    root = tmp_path_factory.mktemp("deployed-fz")
    return registered_champion(new_store(empty_store, root), root, axes=("fz",))
