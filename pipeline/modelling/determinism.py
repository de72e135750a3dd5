"""The deterministic torch settings the networks train and run under, and exact square roots.

torch is imported inside the functions, so importing this module stays cheap.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import torch

# One intra-op thread: on these tiny layers two threads were 15-20 % slower (measured on the 2-core
# CI box, which other jobs share), and a fixed count keeps the order of float reductions, hence the
# weights, the same on any machine (1 and 2 threads happen to agree at the default sizes; larger
# layers cross torch's parallel grain and would not).
TRAIN_THREADS = 1


def _set_deterministic(mode: bool, warn_only: bool = False) -> None:
    """`torch.use_deterministic_algorithms`, minus its import of torch._inductor (~0.95 s measured, per
    process) when inductor is not loaded: that import only sets inductor's own flag, which matters
    for torch.compile alone, unused here. With inductor loaded, the public call keeps both in step."""
    import sys

    import torch

    setter = getattr(torch._C, "_set_deterministic_algorithms", None)
    if setter is None or "torch._inductor.config" in sys.modules:
        torch.use_deterministic_algorithms(mode, warn_only=warn_only)
    else:
        setter(mode, warn_only=warn_only)


def exact_sqrt(t: torch.Tensor) -> torch.Tensor:
    """The square root of each element, correctly rounded (IEEE), as a new tensor. torch's own sqrt
    (float32 and float64, even under `ATEN_CPU_CAPABILITY=default`) is an approximation whose last
    bits depend on the CPU: measured here, 17 % of float32 roots off by an ulp, a different 17 % on
    an emulated older CPU (docs/reproducibility.md). numpy's is the hardware's exact one."""
    import numpy as np
    import torch

    return torch.as_tensor(np.sqrt(t.detach().numpy()), dtype=t.dtype)


@contextmanager
def exact_lbfgs() -> Iterator[None]:
    """torch.optim.LBFGS's strong-Wolfe line search with `exact_sqrt` in its cubic interpolation (its
    only square root), restored on exit: the step it picks then does not depend on the CPU."""
    from torch.optim import lbfgs

    original = lbfgs._cubic_interpolate

    def cubic_interpolate(x1, f1, g1, x2, f2, g2, bounds=None):  # type: ignore[no-untyped-def]
        # torch's own, line for line (torch/optim/lbfgs.py), but for the square root
        if bounds is not None:
            xmin_bound, xmax_bound = bounds
        else:
            xmin_bound, xmax_bound = (x1, x2) if x1 <= x2 else (x2, x1)
        d1 = g1 + g2 - 3 * (f1 - f2) / (x1 - x2)
        d2_square = d1**2 - g1 * g2
        if d2_square >= 0:
            d2 = exact_sqrt(d2_square)
            if x1 <= x2:
                min_pos = x2 - (x2 - x1) * ((g2 + d2 - d1) / (g2 - g1 + 2 * d2))
            else:
                min_pos = x1 - (x1 - x2) * ((g1 + d2 - d1) / (g1 - g2 + 2 * d2))
            return min(max(min_pos, xmin_bound), xmax_bound)
        return (xmin_bound + xmax_bound) / 2.0

    lbfgs._cubic_interpolate = cubic_interpolate
    try:
        yield
    finally:
        lbfgs._cubic_interpolate = original


@contextmanager
def deterministic_torch(seed: int | None = None, threads: int | None = None) -> Iterator[None]:
    """Fixed thread count, deterministic algorithms, oneDNN off and (optionally) a seeded global RNG,
    all restored on exit so a caller's own torch state is untouched. oneDNN (torch's CPU LSTM) picks
    its kernels and blocking by the CPU it finds; without it, torch's own kernels and MKL run, whose
    code paths `pipeline.execution.run` pins, so the weights are the same bytes on any machine."""
    import torch

    prev_threads = torch.get_num_threads()
    prev_onednn = torch.backends.mkldnn.enabled
    prev_det = torch.are_deterministic_algorithms_enabled()
    prev_warn = torch.is_deterministic_algorithms_warn_only_enabled()
    torch.set_num_threads(threads or TRAIN_THREADS)
    torch.backends.mkldnn.enabled = False
    _set_deterministic(True)
    try:
        with torch.random.fork_rng(devices=[]):
            if seed is not None:
                torch.manual_seed(seed)
            yield
    finally:
        _set_deterministic(prev_det, warn_only=prev_warn)
        torch.backends.mkldnn.enabled = prev_onednn
        torch.set_num_threads(prev_threads)
