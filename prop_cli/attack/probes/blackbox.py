"""T0 at scale: ``--blackbox N`` uniform random keys (default 1M), streamed through ``probe_keys_stream``.

Each chunk of keys is screened on ``--blackbox-screen`` samples in bf16; the keys with the highest
divergence (what an attacker without targets ranks by) and, with the owner's targets, the highest
screening leakage are kept and re-scored exactly on every audit sample. The row's worst leakage is
over the re-scored keys; its pick is the attacker's (largest divergence). A few thousand random keys
(``random``) miss the rare keys that leak: they sit far from the user's code, where training never
looked. Control: the kept keys where no user was enrolled (``ProbeContext.unenrolled``).
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import torch

from .base import Group, Probe, ProbeContext

CHUNK = 2048  # keys per screening chunk: the working set stays in cache
TOP_REPORTED = 10


def _chunks(ctx: ProbeContext, total: int) -> Iterator[np.ndarray]:
    rng = ctx.rng()
    bits = ctx.km.encoder.code_bits
    # A large policy screens a few keys at a time (its rows per forward), so the budget is checked often;
    # the keys drawn are the same.
    rows = ctx.km.max_rows
    step = CHUNK if rows is None else max(1, min(CHUNK, rows // max(1, ctx.settings.blackbox_screen)))
    for start in range(0, total, CHUNK):
        keys = rng.integers(0, 2, (min(CHUNK, total - start), bits), dtype=np.uint8)
        yield from (keys[i : i + step] for i in range(0, len(keys), step))


def run(ctx: ProbeContext) -> list[Group]:
    s = ctx.settings
    if not s.blackbox:
        return []
    scan = ctx.probe_keys_stream(
        _chunks(ctx, s.blackbox), s.blackbox, "blackbox", screen=s.blackbox_screen, keep=s.blackbox_keep
    )
    v = scan.values
    wall, cpu = scan.seconds["scan"], scan.seconds["scan_cpu"]
    evals = scan.scanned * scan.screen_samples
    info = {
        "scanned": scan.scanned,
        "screen_samples": scan.screen_samples,
        "rescored": int(len(scan.bits)),
        "path": scan.path,
        "seconds": scan.seconds,
        "keys_per_second": scan.scanned / wall if wall else None,
        "evaluations_per_second": evals / wall if wall else None,
        # per CPU-second (all threads): what the scan costs on a machine other work also uses
        "evaluations_per_cpu_second": evals / cpu if cpu else None,
    }
    order = torch.argsort(v["divergence"], descending=True)[:TOP_REPORTED]
    top = [{"divergence": float(v["divergence"][i]), "fidelity": float(v["fidelity"][i])} for i in order]
    if "leakage" in v:
        for t, i in zip(top, order):
            t["leakage"] = float(v["leakage"][i])
    if ctx.has_key:  # how far the top keys' codes are from the user's (0 = the user's behaviour itself)
        user = ctx.codes(ctx.keys[0])
        dist = (ctx.codes(scan.bits[order.numpy()]) != user).sum(1)
        for t, dd in zip(top, dist):
            t["code_distance"] = int(dd)
    info["top_by_divergence"] = top
    return [Group("blackbox", v, is_key=True, search=info, bits=scan.bits)]


def control(ctx: ProbeContext, found: list[Group]) -> list[Group]:
    return [Group("blackbox", ctx.on(ctx.unenrolled).probe_keys(g.bits, "blackbox control"), is_key=True)
            for g in found if g.bits is not None]  # fmt: skip


PROBE = Probe(
    "blackbox", "T0", "key",
    "--blackbox random keys streamed: screened in bf16, the top re-scored exactly", run, control=control,
)  # fmt: skip
