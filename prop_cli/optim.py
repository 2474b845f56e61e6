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
    """``torch.optim.Adam(groups, lr, foreach=True)``: ``params`` is a list of tensors, or of groups
    ``{"params": [...], "lr": ...}`` (a group without "lr" takes ``lr``). ``set_lr_factor`` scales every
    group's learning rate, as ``torch.optim.lr_scheduler.LambdaLR`` does."""

    def __init__(
        self,
        params: list,
        lr: float,
        betas: tuple[float, float] = (0.9, 0.999),
        eps: float = 1e-8,
    ) -> None:
        groups = params if params and isinstance(params[0], dict) else [{"params": params}]
        self.groups = [
            {"params": [p for p in g["params"] if p.requires_grad], "lr": g.get("lr", lr)} for g in groups
        ]
        self.base_lrs = [g["lr"] for g in self.groups]
        self.beta1, self.beta2 = betas
        self.eps = eps
        self.t = 0
        for g in self.groups:
            g["m"] = [torch.zeros_like(p) for p in g["params"]]
            g["v"] = [torch.zeros_like(p) for p in g["params"]]

    def set_lr_factor(self, factor: float) -> None:
        for g, base in zip(self.groups, self.base_lrs):
            g["lr"] = base * factor

    def zero_grad(self) -> None:
        for g in self.groups:
            for p in g["params"]:
                p.grad = None

    @torch.no_grad()
    def step(self) -> None:
        if not any(p.grad is not None for g in self.groups for p in g["params"]):
            return
        self.t += 1
        bc1 = 1 - self.beta1**self.t
        bc2 = 1 - self.beta2**self.t
        for g in self.groups:
            live = [i for i, p in enumerate(g["params"]) if p.grad is not None]
            if not live:
                continue
            ps = [g["params"][i] for i in live]
            gs = [p.grad for p in ps]
            ms = [g["m"][i] for i in live]
            vs = [g["v"][i] for i in live]
            torch._foreach_lerp_(ms, gs, 1 - self.beta1)
            torch._foreach_mul_(vs, self.beta2)
            torch._foreach_addcmul_(vs, gs, gs, 1 - self.beta2)
            denom = torch._foreach_sqrt(vs)
            torch._foreach_div_(denom, math.sqrt(bc2))
            torch._foreach_add_(denom, self.eps)
            torch._foreach_addcdiv_(ps, ms, denom, -g["lr"] / bc1)


def cosine_lr(base: float, step: int, total: int, floor: float) -> float:
    """Cosine decay from ``base`` to ``base * floor`` over ``total`` steps."""
    return base * (floor + (1 - floor) * 0.5 * (1 + math.cos(math.pi * min(step, total) / total)))
