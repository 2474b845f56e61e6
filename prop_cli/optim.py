"""Adam with a cosine learning-rate schedule, without ``torch.optim``.

``torch.optim.Optimizer`` imports ``torch._dynamo`` on its first call (its methods are wrapped to
disable the compiler), which costs about 2 s per process on these machines: more than a tenth of
a whole IL personalization. This is the same update as ``torch.optim.Adam`` (no weight decay,
no amsgrad), on foreach kernels, and a test checks it step for step against torch's.
"""

from __future__ import annotations

import math

import torch


class Adam:
    def __init__(
        self,
        params: list[torch.Tensor],
        lr: float,
        betas: tuple[float, float] = (0.9, 0.999),
        eps: float = 1e-8,
    ) -> None:
        self.params = [p for p in params if p.requires_grad]
        self.lr = lr
        self.beta1, self.beta2 = betas
        self.eps = eps
        self.t = 0
        self.m = [torch.zeros_like(p) for p in self.params]
        self.v = [torch.zeros_like(p) for p in self.params]

    def zero_grad(self) -> None:
        for p in self.params:
            p.grad = None

    @torch.no_grad()
    def step(self) -> None:
        live = [i for i, p in enumerate(self.params) if p.grad is not None]
        if not live:
            return
        self.t += 1
        ps = [self.params[i] for i in live]
        gs = [self.params[i].grad for i in live]
        ms = [self.m[i] for i in live]
        vs = [self.v[i] for i in live]
        torch._foreach_lerp_(ms, gs, 1 - self.beta1)
        torch._foreach_mul_(vs, self.beta2)
        torch._foreach_addcmul_(vs, gs, gs, 1 - self.beta2)
        bc1 = 1 - self.beta1**self.t
        bc2 = 1 - self.beta2**self.t
        denom = torch._foreach_sqrt(vs)
        torch._foreach_div_(denom, math.sqrt(bc2))
        torch._foreach_add_(denom, self.eps)
        torch._foreach_addcdiv_(ps, ms, denom, -self.lr / bc1)


def cosine_lr(base: float, step: int, total: int, floor: float) -> float:
    """Cosine decay from ``base`` to ``base * floor`` over ``total`` steps."""
    return base * (floor + (1 - floor) * 0.5 * (1 + math.cos(math.pi * min(step, total) / total)))
