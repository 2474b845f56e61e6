"""T1: a relaxed code in [-1, 1]^n optimised through the encoder, then rounded to ±1 and probed too.

With the default hashed encoding the encoder's input is SHAKE-256(key), so this searches the code
space: at least as strong as searching keys (a rounded code need not be reachable by any key). With
raw encoding the code is the key. The search maximises divergence from the reference on the inputs
only; it never sees the owner's targets.

Two rows. ``relaxed-rounded``: the codes the restarts round to, and their negations, are concrete codes
anyone holding the files can feed to the encoder, so they are a key row, scored like keys; their control
is the same codes where no user was enrolled (the reference itself). ``relaxed``: the unrounded codes, a
search row, scored on bounded leakage (a move larger than the user's is scaled back to it, so neither
side reaches 1 by moving far) against what the same attacker reaches without the bundle: the same search
budget spent on the original checkpoint's deltas directly (T2's search, within the encoder's range). Not
this search through the bundle's encoder on the original: the encoder is part of the bundle and carries
the user's behaviour into such a "control" (it reached 0.53-0.60 on the IL example), which hid leakage.
"""

from __future__ import annotations

from dataclasses import replace

import torch

from . import latent
from .base import Group, Probe, ProbeContext, codes_unenrolled, maximise_divergence


def run(ctx: ProbeContext) -> list[Group]:
    s = ctx.settings
    n = ctx.km.encoder.code_bits
    u = torch.rand(s.restarts, n, generator=ctx.generator()).clamp(0.02, 0.98)
    theta = torch.logit(u).to(ctx.ref.x.device).requires_grad_(True)

    def codes() -> torch.Tensor:
        return torch.tanh(theta / 2)  # = 2 * sigmoid(theta) - 1: the relaxed key u mapped to ±1

    maximise_divergence(ctx, [theta], lambda: ctx.km.layer_deltas(codes()), "relaxed")
    relaxed = codes().detach()
    # Both signs of each rounded code: the encoder is nearly odd in the code (docs/privacy.md, "Wrong keys
    # in closed loop"), so the largest divergence lies at the user's code or at its antipode, which runs
    # the user's change negated (on the demo's default IL bundle 19 of 128 restarts ended there, 128 bits
    # from the user's code, and none at the code itself).
    rounded = torch.where(relaxed >= 0, 1.0, -1.0)
    rounded = torch.cat([rounded, -rounded])
    search = {"restarts": s.restarts, "steps": s.search_steps}
    rounded_search = dict(search)
    if ctx.has_key:  # 0 = the search found the user's own code (for raw encoding: the key)
        rounded_search["code_distance"] = [int(c) for c in (rounded != ctx.codes(ctx.keys[0])).sum(1)]
    return [
        Group("relaxed", ctx.probe_codes(relaxed, "relaxed"), is_key=False, search=search),
        Group(
            "relaxed-rounded",
            ctx.probe_codes(rounded, "relaxed"),
            is_key=ctx.encoding == "raw",
            search=rounded_search,
            codes=rounded,
            kind="key",
        ),
    ]


def control(ctx: ProbeContext, found: list[Group]) -> list[Group]:
    out = codes_unenrolled(ctx, [g for g in found if g.kind == "key"])
    if ctx.original is not None:  # T2's own control search (its restarts): run once for both rows
        [direct] = latent.run(replace(ctx.on(ctx.original), probe=latent.PROBE.name))
        out += [Group(g.name, direct.values, is_key=False, search=direct.search)
                for g in found if g.kind is None]  # fmt: skip
    return out


PROBE = Probe(
    "relaxed", "T1", "search",
    "a continuous code optimised through the encoder (--restarts, --search-steps), and its rounding", run,
    control=control,
)  # fmt: skip
