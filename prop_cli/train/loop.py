"""The one step loop and the one optimiser stack every recipe trains with.

``Optimiser``: Adam (``optim.Adam``, the fused kernel without ``torch.optim``'s 2 s import) over
parameter groups, its learning rate cosine-decayed from ``lr`` to ``lr * lr_floor``, with an optional
gradient-norm clip (LeRobot's own training loop clips at 10). ``run_steps`` calls a recipe's step
``steps`` times and reports progress, under ``mixed_precision``'s autocast.

Mixed precision (``--precision bf16``) is autocast as Accelerate and LeRobot (``--policy.use_amp``) do
it: the forward and the loss run in bfloat16 where torch deems it safe, while the parameters, their
gradients and Adam's moments stay fp32 (the updates accumulate in fp32; the bundle keeps the
checkpoint's dtypes, as with fp32). It is applied here, around every recipe's step, rather than in
each recipe. No gradient scaler: bf16 has fp32's exponent range, so gradients do not underflow as
fp16's do.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable

import torch

from prop_cli.errors import PropError

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
        # The step calls this inside the loop's autocast; torch advises against backward under it (the
        # backward ops follow the forward's dtypes anyway), and the clip and Adam must see fp32.
        with torch.autocast(loss.device.type, enabled=False):
            loss.backward()
            if self.reduce is not None:
                self.reduce(self.params)
            if self.clip is not None:
                torch.nn.utils.clip_grad_norm_(self.params, self.clip)
            self.adam.step()
        self.t += 1
        self.adam.set_lr_factor(cosine_lr(1.0, self.t, self.steps, self.lr_floor))


def mixed_precision(precision: str, device: torch.device | str) -> contextlib.AbstractContextManager:
    """The context a step's forward and loss run in: nothing for fp32, bf16 autocast on ``device``."""
    if precision == "fp32":
        return contextlib.nullcontext()
    dev = torch.device(device)
    # Native bf16 from Ampere (compute capability 8.0) on; older GPUs emulate it slower than fp32.
    if dev.type == "cuda" and not torch.version.hip and torch.cuda.get_device_capability(dev) < (8, 0):
        raise PropError(
            f"--precision bf16: {torch.cuda.get_device_name(dev)} has no bfloat16 arithmetic",
            "use --precision fp32 on this GPU",
        )
    return torch.autocast(dev.type, dtype=torch.bfloat16)


def run_steps(
    step: Callable[[], dict[str, float]],
    steps: int,
    progress: Progress | None,
    precision: str = "fp32",
    device: torch.device | str = "cpu",
) -> dict[str, float]:
    """``step()`` (one update; returns its losses) ``steps`` times, each under ``precision`` on
    ``device`` (``mixed_precision``); returns the last losses."""
    amp = mixed_precision(precision, device)
    # A zero-initialised layer (the encoder's head, a LoRA B) and tiny late gradients drive Adam's moments
    # into denormal floats, which made CPU steps ~10x slower; flushing them to zero costs no accuracy.
    flush = torch.set_flush_denormal(True)
    losses: dict[str, float] = {}
    try:
        for i in range(steps):
            with amp:
                losses = step()
            if progress is not None:
                progress(i + 1, losses)
    finally:
        if flush:
            torch.set_flush_denormal(False)
    return losses
