"""T2: delta of every keyed layer optimised directly, within the encoder's range (1 - scale, 1 + scale).

Its control is the same search on the original checkpoint (same keyed layers, same range, same
restarts): what it finds there comes from the task and the metric, not from the bundle.
"""

from __future__ import annotations

import torch

from .base import Group, Probe, ProbeContext, maximise_divergence, on_original


def _same_search(ctx: ProbeContext) -> tuple:
    """What decides this search's outcome: the model's tensors (by identity and version: a sealed bundle's
    attacked model and its control share the base's), its keyed layers, the encoder's range, the samples,
    the settings and the probe's random stream. Two runs with equal keys compute the same, bit for bit."""
    km, s = ctx.km, ctx.settings
    tensors = tuple((id(t), t._version) for t in (*km.module.parameters(), *km.module.buffers()))
    return ("latent", type(km.module), tensors, tuple(km.layer_names), tuple(sorted(km.batch_axis.items())),
            float(km.encoder.scale), tuple(km.encoder.features), id(ctx.ref.x), id(ctx.ref.b), ctx.probe,
            s.seed, s.restarts, s.search_steps, s.search_lr, s.search_batch)  # fmt: skip


SHARED = "same model as control: the search measured once, for this row and its control"


def run(ctx: ProbeContext) -> list[Group]:
    """The search, or its result where the same search already ran in this audit: to its end, or, where
    the attacked model is its control's (``ProbeContext.shared_searches``: a sealed bundle's base, keyed
    at the same layers and range), as far as the budget let it, since the row and its control are then
    one computation and running it again would only give one of them another share of the budget."""
    key = _same_search(ctx)
    done = ctx.kept.get(key)
    if done is not None and (done[2] or ctx.shared_searches):
        if ctx.shared_searches:
            ctx.shortcut(SHARED)
        return [Group("latent", dict(done[0]), is_key=False, search=dict(done[1]))]
    cut = len(ctx.cut)
    [group] = _search(ctx)
    # held with the model and inputs, so that their ids stay theirs while the key is kept
    ctx.kept[key] = (group.values, group.search, len(ctx.cut) == cut, ctx.km.module, ctx.ref.x)
    if ctx.shared_searches:
        ctx.shortcut(SHARED)
    return [group]


def known(ctx: ProbeContext) -> bool:
    """Whether this search, and its control's, would reuse a search that already ran (``run``)."""
    done = ctx.kept.get(_same_search(ctx))
    return (
        done is not None
        and (done[2] or ctx.shared_searches)
        and (ctx.original is None or ctx.kept.get(_same_search(ctx.on(ctx.original))) is done)
    )


def _search(ctx: ProbeContext) -> list[Group]:
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
    control=on_original(run), known=known,
)  # fmt: skip
