"""The deterministic torch settings networks train and run under."""

from __future__ import annotations

import torch

from pipeline.modelling.networks import deterministic_torch


def test_deterministic_torch_pins_then_restores_the_callers_settings() -> None:
    # given: a caller with its own torch settings
    torch.set_num_threads(2)
    torch.backends.mkldnn.enabled = True
    # when: code runs inside deterministic_torch
    with deterministic_torch(seed=0):
        inside = (
            torch.get_num_threads(),
            torch.backends.mkldnn.enabled,
            torch.are_deterministic_algorithms_enabled(),
        )
        first = torch.rand(3)
    with deterministic_torch(seed=0):
        second = torch.rand(3)
    # then: one thread, oneDNN off (it picks kernels by CPU), deterministic algorithms, a seeded RNG
    assert inside == (1, False, True)
    assert torch.equal(first, second)
    # and the caller's settings are back
    assert torch.get_num_threads() == 2 and torch.backends.mkldnn.enabled
    assert not torch.are_deterministic_algorithms_enabled()
