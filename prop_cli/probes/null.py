"""T0: no key at all (delta = 1 everywhere): what everyone gets."""

from __future__ import annotations

import torch

from .base import Group, Probe, ProbeContext


def run(ctx: ProbeContext) -> list[Group]:
    ones = [torch.ones(1, f, device=ctx.ref.x.device) for f in ctx.km.encoder.features]
    return [Group("null", ctx.probe_deltas(ones), is_key=True)]


PROBE = Probe("null", "T0", "key", "no key: the base behaviour everyone gets", run)
