"""The deterministic torch settings networks train and run under."""

from __future__ import annotations

import pytest
import torch

from pipeline.modelling.determinism import deterministic_torch, exact_lbfgs, exact_sqrt


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


def test_exact_sqrt_is_correctly_rounded_in_float32_and_float64() -> None:
    # given: float32 values spread over many binades, and float64 scalars (0-dim, as LBFGS has them)
    import math

    import numpy as np

    values = np.random.default_rng(0).uniform(-20, 20, 20_000)
    f32 = torch.from_numpy((2.0**values).astype(np.float32))
    # when: their exact square roots are taken
    roots = exact_sqrt(f32)
    # then: each is the float64 root rounded once to float32 (exact: 53 >= 2 * 24 + 2 bits), dtype kept
    assert roots.dtype == torch.float32
    assert np.array_equal(roots.numpy(), np.sqrt(f32.numpy().astype(np.float64)).astype(np.float32))
    for v in 2.0 ** values[:200]:
        assert float(exact_sqrt(torch.tensor(v, dtype=torch.float64))) == math.sqrt(v)


def test_exact_lbfgs_swaps_the_line_search_root_only_while_it_runs() -> None:
    # given: torch's own cubic interpolation of the strong-Wolfe line search
    from torch.optim import lbfgs

    original = lbfgs._cubic_interpolate
    args = (torch.tensor(0.0, dtype=torch.float64), 1.0, torch.tensor(-2.0, dtype=torch.float64))
    args += (torch.tensor(1.0, dtype=torch.float64), 0.5, torch.tensor(0.7, dtype=torch.float64))
    # when: it runs inside exact_lbfgs
    with exact_lbfgs():
        swapped = lbfgs._cubic_interpolate
        ours = float(swapped(*args))
    # then: the step is torch's formula (to within torch's root's last bits), and torch's is back after
    assert swapped is not original and lbfgs._cubic_interpolate is original
    assert ours == pytest.approx(float(original(*args)), rel=1e-12)
