"""The networks' optimiser: Adam, bit for bit torch's, on one flat buffer of parameters."""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from typing import TYPE_CHECKING

from pipeline.modelling.determinism import exact_sqrt

if TYPE_CHECKING:
    import torch


def flatten(params: Sequence[torch.nn.Parameter]) -> torch.Tensor:
    """One buffer holding the values of `params`, each parameter now a view of its own slice (values
    unchanged). An elementwise update of every parameter (an optimizer step, a running average) is
    then one op on the buffer rather than one per parameter: the same arithmetic element for element,
    so the same bits, at a fraction of the per-op overhead that dominates these small networks."""
    import torch

    with torch.no_grad():
        flat = torch.cat([p.detach().reshape(-1) for p in params])
        offset = 0
        for p in params:
            p.data = flat[offset : offset + p.numel()].view_as(p)
            offset += p.numel()
    return flat


class Adam:
    """Adam (Kingma & Ba), the arithmetic of torch.optim.Adam's single-tensor CPU path op for op
    (L2 `weight_decay` added to the gradient, as there) but for an exact square root (`exact_sqrt`:
    torch's depends on the CPU); a test checks the two agree bit for bit given the same root. The
    parameters are `flatten`ed: each step is a few ops on one buffer, whatever the layer count.

    Why not torch.optim.Adam itself: every torch.optim optimizer imports torch._dynamo on first
    use (~1 s measured per process, for torch.compile support unused here), and the 12 network
    stages each pay it; this one needs only tensor ops.
    """

    def __init__(
        self,
        params: Iterator[torch.nn.Parameter] | Sequence[torch.nn.Parameter],
        lr: float,
        betas: tuple[float, float] = (0.9, 0.999),
        eps: float = 1e-8,
        weight_decay: float = 0.0,
    ) -> None:
        import torch

        self.params = list(params)
        self.flat = flatten(self.params)
        self.lr, (self.beta1, self.beta2), self.eps, self.weight_decay = lr, betas, eps, weight_decay
        self.exp_avg = torch.zeros_like(self.flat)
        self.exp_avg_sq = torch.zeros_like(self.flat)
        self.steps = 0

    def zero_grad(self) -> None:
        for p in self.params:
            p.grad = None

    def step(self) -> None:
        import torch

        grads = [p.grad for p in self.params]
        if any(g is None for g in grads):  # every parameter of these networks is in the loss
            missing = [i for i, g in enumerate(grads) if g is None]
            raise ValueError(f"Adam: parameter(s) {missing} have no gradient; run backward() first")
        self.steps += 1
        bias_correction1 = 1 - self.beta1**self.steps
        bias_correction2_sqrt = (1 - self.beta2**self.steps) ** 0.5
        step_size = self.lr / bias_correction1
        with torch.no_grad():
            grad = torch.cat([g.reshape(-1) for g in grads])  # type: ignore[union-attr]
            if self.weight_decay != 0:
                grad = grad.add(self.flat, alpha=self.weight_decay)
            self.exp_avg.lerp_(grad, 1 - self.beta1)
            self.exp_avg_sq.mul_(self.beta2).addcmul_(grad, grad, value=1 - self.beta2)
            denom = exact_sqrt(self.exp_avg_sq).div_(bias_correction2_sqrt).add_(self.eps)
            self.flat.addcdiv_(self.exp_avg, denom, value=-step_size)
