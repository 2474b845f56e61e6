"""T0: no key at all (delta = 1 everywhere): what everyone gets."""

from __future__ import annotations

import numpy as np

from .base import Group, Probe, ProbeContext, on_unenrolled


def run(ctx: ProbeContext) -> list[Group]:
    none = np.zeros((0, ctx.km.encoder.code_bits), np.uint8)
    return [Group("null", ctx.probe_keys(none, "null", null=1), is_key=True)]


PROBE = Probe(
    "null", "T0", "key", "no key: the base behaviour everyone gets", run, control=on_unenrolled(run)
)
