"""The float32 module a kind's runtime hands the ONNX export: its network between the checkpoint's
standardisation of inputs and targets."""

from __future__ import annotations

import functools
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import torch


@functools.cache
def _standardised_class() -> type:
    """Defined lazily so that importing this file skips torch."""
    from torch import nn

    class Deployable(nn.Module):
        """(inputs - x_mean) / x_std -> net -> * y_std + y_mean, in float32; `net` alone unscaled."""

        def __init__(self, net: nn.Module, pre: dict[str, Any] | None) -> None:
            super().__init__()
            self.net = net
            self.scaled = pre is not None
            if pre is not None:
                for key in ("x_mean", "x_std", "y_mean", "y_std"):
                    self.register_buffer(key, pre[key].float().clone())

        def forward(self, x: torch.Tensor) -> torch.Tensor:
            if not self.scaled:
                return self.net(x)
            return self.net((x - self.x_mean) / self.x_std) * self.y_std + self.y_mean

    return Deployable


def standardised(net: torch.nn.Module, pre: dict[str, Any] | None) -> torch.nn.Module:
    """`net` behind the checkpoint's standardisation `pre` (None: it reads the inputs as they are),
    float32, in eval mode."""
    return _standardised_class()(net, pre).float().eval()
