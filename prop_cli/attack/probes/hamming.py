"""T0: keys exactly d bits from the user's, for each d of ``--hamming`` (all of them when few exist)."""

from __future__ import annotations

from prop_cli.core.key_sampling import neighbours_at

from .base import Group, Probe, ProbeContext, on_unenrolled


def run(ctx: ProbeContext) -> list[Group]:
    rng = ctx.rng()
    groups = []
    for d in ctx.settings.hamming or []:
        if groups and ctx.out_of_time(f"hamming {d}"):  # the budget: the distances done so far
            break
        near = neighbours_at(ctx.keys[0], d, ctx.settings.per_distance, rng)
        values = ctx.probe_keys(near, f"hamming {d}")
        groups.append(Group(f"hamming {d}", values, is_key=True, distance=d))
    return groups


PROBE = Probe(
    "hamming", "T0", "key", "keys d bits from yours, for each d of --hamming (--per-distance each)", run,
    control=on_unenrolled(run), needs="key",
)  # fmt: skip
