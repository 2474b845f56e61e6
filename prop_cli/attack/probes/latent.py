"""T2: delta of every keyed layer optimised directly, within the encoder's range (1 - scale, 1 + scale).

Its control is the same search on the original checkpoint (same keyed layers, same range, same
restarts): what it finds there comes from the task and the metric, not from the bundle.
"""

from __future__ import annotations

import torch

from .base import Group, Probe, ProbeContext, maximise_divergence, on_original


def run(ctx: ProbeContext) -> list[Group]:
    s = ctx.settings
    scale = ctx.km.encoder.scale
    gen = ctx.generator()
    phis = [
        torch.randn(s.restarts, d, generator=gen).to(ctx.ref.x.device).requires_grad_(True)
        for d in ctx.km.encoder.features
    ]

    def deltas() -> list[torch.Tensor]:
        return [1.0 + scale * torch.tanh(p) for p in phis]

    maximise_divergence(ctx, phis, deltas, "latent")
    values = ctx.probe_deltas([d.detach() for d in deltas()], "latent")
    return [Group("latent", values, is_key=False, search={"restarts": s.restarts, "steps": s.search_steps})]


PROBE = Probe(
    "latent", "T2", "search", "each keyed layer's delta optimised directly, skipping the encoder", run,
    control=on_original(run),
)  # fmt: skip
