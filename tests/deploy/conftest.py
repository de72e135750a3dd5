"""Fixtures of the deployed model's tests: a champion on rest-relative volts, registered with a unit
calibrated with it on its FSRs' conductance, and a held-out trial of that unit; and the same of a model
of fz alone (a load cell's reference)."""

from __future__ import annotations

import pytest

from tests.deploy.builders import Champion, registered_champion


@pytest.fixture(scope="package")
def champion(tmp_path_factory: pytest.TempPathFactory) -> Champion:
    """Registered once for the package's tests, in a store of its own."""
    return registered_champion(tmp_path_factory.mktemp("deployed"))


@pytest.fixture(scope="package")
def fz_champion(tmp_path_factory: pytest.TempPathFactory) -> Champion:
    """The champion of a lab whose reference recorded fz alone, in a store of its own."""
    return registered_champion(tmp_path_factory.mktemp("deployed-fz"), axes=("fz",))
