"""T0: uniform random keys (``--random N``)."""

from __future__ import annotations

from prop_cli.core.key_sampling import random_keys

from .base import Group, Probe, ProbeContext, on_unenrolled


def run(ctx: ProbeContext) -> list[Group]:
    n = ctx.settings.random
    if not n:
        return []
    keys = random_keys(n, ctx.km.encoder.code_bits, ctx.rng(), exclude=ctx.keys[:1] or None)
    return [Group("random", ctx.probe_keys(keys, "random"), is_key=True)]


PROBE = Probe("random", "T0", "key", "--random uniform random keys", run, control=on_unenrolled(run))
