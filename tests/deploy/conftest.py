"""Fixtures of the deployed model's tests: a champion on rest-relative volts, registered with a unit
calibrated with it on its FSRs' conductance, and a held-out trial of that unit."""

from __future__ import annotations

import pytest

from tests.deploy.builders import Champion, registered_champion


@pytest.fixture(scope="package")
def champion(tmp_path_factory: pytest.TempPathFactory) -> Champion:
    """Registered once for the package's tests, in a store of its own."""
    return registered_champion(tmp_path_factory.mktemp("deployed"))
