"""The one step loop and the one optimiser stack every recipe trains with.

``Optimiser``: Adam (``optim.Adam``, the fused kernel without ``torch.optim``'s 2 s import) over
parameter groups, its learning rate cosine-decayed from ``lr`` to ``lr * lr_floor``, with an optional
gradient-norm clip (LeRobot's own training loop clips at 10). ``run_steps`` calls a recipe's step
``steps`` times and reports progress.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from .optim import Adam, cosine_lr

Progress = Callable[[int, dict[str, float]], None]  # (step, latest losses)


class Optimiser:
    """One update per ``update(loss)``: zero the gradients, backpropagate, clip, step, decay the rate."""

    def __init__(
        self, groups: list, lr: float, steps: int, lr_floor: float, clip: float | None = None,
        reduce: Callable[[list[torch.Tensor]], None] | None = None,
    ) -> None:  # fmt: skip
        self.adam = Adam(groups, lr=lr)
        self.params = [p for g in self.adam.groups for p in g["params"]]
        self.steps, self.lr_floor, self.clip = steps, lr_floor, clip
        self.reduce = reduce  # several processes: sum the gradients over them (``distributed``)
        self.t = 0

    def update(self, loss: torch.Tensor) -> None:
        self.adam.zero_grad()
        loss.backward()
        if self.reduce is not None:
            self.reduce(self.params)
        if self.clip is not None:
            torch.nn.utils.clip_grad_norm_(self.params, self.clip)
        self.adam.step()
        self.t += 1
        self.adam.set_lr_factor(cosine_lr(1.0, self.t, self.steps, self.lr_floor))


def run_steps(
    step: Callable[[], dict[str, float]], steps: int, progress: Progress | None
) -> dict[str, float]:
    """``step()`` (one update; returns its losses) ``steps`` times; returns the last losses."""
    # A zero-initialised layer (the encoder's head, a LoRA B) and tiny late gradients drive Adam's moments
    # into denormal floats, which made CPU steps ~10x slower; flushing them to zero costs no accuracy.
    flush = torch.set_flush_denormal(True)
    losses: dict[str, float] = {}
    try:
        for i in range(steps):
            losses = step()
            if progress is not None:
                progress(i + 1, losses)
    finally:
        if flush:
            torch.set_flush_denormal(False)
    return losses
