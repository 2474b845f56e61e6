"""T3 few-shot code fit: how often it finds the user's code, against k, restarts and steps.

    python -m benchmarks.bench_fewshot_hits BUNDLE --data D --key-file K [--original CKPT] [--pool 64]
                                                   [--steps 100,200,400] [--seed 0]
    python -m benchmarks.bench_fewshot_hits BUNDLE --data D --key-file K --compare 4 [--draws 3]

The audit's few-shot probe (``prop_cli.attack.probes.fewshot``) fits the encoder's input code to k of
the user's labelled rows (outside the audit sample), from ``RESTARTS`` random starts for ``STEPS`` Adam
steps, and keeps the restart with the lowest fit loss on those k rows (all the attacker can see). Here
each (k, steps) runs one pool of ``--pool`` restarts; restarts are independent (per-restart loss,
elementwise Adam), so the chance that the attacker's pick among R restarts finds the code (its rounding
leaks > 0.5 on the audit samples) is estimated from random R-subsets of the pool. The pick's mean
leakage is printed beside it. The audit's default (docs/audit.md, "Few-shot budget") was chosen from
this table: where more restarts or steps stop finding more.

``--compare K``: the audit's own few-shot rows at k = K (its default budget), next to ``--draws``
independent code fits of 16 restarts x 200 steps on the same K rows (other seeds), each scored like the
audit's rounded code: does the audit find at least what such an attacker finds?
"""

from __future__ import annotations

import argparse
import os
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

SIZES = (8, 16, 32, 64, 128, 256)
HIT = 0.5
DRAWS = 2000


def pick_stats(leak: np.ndarray, loss: np.ndarray, r: int, seed: int = 0) -> tuple[float, float]:
    """(P(pick leaks > HIT), E[pick's leakage]) for the lowest-loss restart among r of the pool."""
    if r >= len(leak):
        i = int(np.argmin(loss))
        return float(leak[i] > HIT), float(leak[i])
    rng = np.random.default_rng(seed)
    sub = np.stack([rng.choice(len(leak), r, replace=False) for _ in range(DRAWS)])
    pick = sub[np.arange(DRAWS), np.argmin(loss[sub], axis=1)]
    return float(np.mean(leak[pick] > HIT)), float(np.mean(leak[pick]))


def context(bundle_path: Path, data: Path, key_file: Path, original: str | None, seed: int):
    """The audit's probe context for this bundle, built as ``prop attack`` builds it."""
    import torch

    from prop_cli.attack import target
    from prop_cli.attack.audit import sample_index, shot_rows
    from prop_cli.attack.probes.base import ProbeContext, Reference
    from prop_cli.bundle import load_bundle
    from prop_cli.config import AuditSettings
    from prop_cli.core.key_files import read_key_file
    from prop_cli.datasources import load_data
    from prop_cli.fit import prepare

    bundle = load_bundle(bundle_path)
    key = read_key_file(key_file, bundle.key_bits)
    ds, _ = prepare(bundle.loaded, load_data(data, require_y=True), "--data", bundle.task)
    km = target.attacked_model(bundle, torch.device("cpu")).requires_grad_(False)
    ref_model = target.load_original(bundle, original) if original else km.module
    s = AuditSettings(seed=seed).validate(bundle.key_bits, True, [])  # the audit's defaults, filled in
    idx = sample_index(ds, s.samples, s.seed)
    x = torch.from_numpy(ds.x[idx])
    p = torch.from_numpy(ds.y[idx])
    if bundle.task == "regression" and p.dim() == 1:
        p = p[:, None]
    with torch.inference_mode():
        b = ref_model(x)
    shots = shot_rows(ds, idx, s.seed, x.device, ref_model, bundle.task)
    ctx = ProbeContext(km, Reference(x, b.clone(), p, bundle.task), s, [key], bundle.key_encoding,
                       shots=shots, probe="fewshot")  # fmt: skip
    return target.probe_context(bundle, ctx)


def audit_parser(prog: str, doc: str | None, original_required: bool = False) -> argparse.ArgumentParser:
    """What the benchmarks that build the audit's context take: a bundle, its data, the user's key."""
    ap = argparse.ArgumentParser(prog=f"python -m benchmarks.{prog}", description=doc)
    ap.add_argument("bundle", type=Path)
    ap.add_argument("--data", type=Path, required=True)
    ap.add_argument("--key-file", type=Path, required=True)
    ap.add_argument("--original", default=None, required=original_required)
    ap.add_argument("--seed", type=int, default=0)
    return ap


def main(argv: list[str] | None = None) -> None:
    ap = audit_parser("bench_fewshot_hits", __doc__)
    ap.add_argument("--pool", type=int, default=64)
    ap.add_argument("--steps", default="100,200,400")
    ap.add_argument("--shots", default="1,4,16,64")
    ap.add_argument("--compare", type=int, default=None, metavar="K")
    ap.add_argument("--draws", type=int, default=3)
    args = ap.parse_args(argv)
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    import torch

    torch.set_num_threads(1)
    from prop_cli.attack.probes import fewshot

    ctx = context(args.bundle, args.data, args.key_file, args.original, args.seed)
    if args.compare is not None:
        compare(ctx, args.compare, args.draws)
        return
    user = ctx.codes(ctx.keys[0])
    sizes = [r for r in SIZES if r <= args.pool]
    print(f"T3 code fit on {args.bundle}: attacker's pick (lowest fit loss) among R restarts of a pool of "
          f"{args.pool}; P(its rounding leaks > {HIT}) / its mean leakage")  # fmt: skip
    head = "  ".join(f"R={r:<9d}" for r in sizes)
    print(f"{'k':>3s}{'steps':>6s}{'per-restart':>12s}{'exact':>7s}  {head}  s/restart")
    for k in [int(v) for v in args.shots.split(",")]:
        if ctx.shots is None or k > len(ctx.shots.x):
            continue
        shots = fewshot.shots_of(ctx, k)
        for steps in [int(v) for v in args.steps.split(",")]:
            t0 = time.perf_counter()
            codes, loss = fewshot.fit_codes(replace(ctx), shots, ctx.generator(), args.pool, steps)
            sec = (time.perf_counter() - t0) / args.pool
            rounded = torch.where(codes >= 0, 1.0, -1.0)
            leak = ctx.probe_codes(rounded, "fewshot")["leakage"].numpy()
            exact = int(((rounded != user).sum(1) == 0).sum())
            stats = [pick_stats(leak, loss.cpu().numpy(), r) for r in sizes]
            cells = "  ".join(f"{hit:.2f} / {mean:.2f} " for hit, mean in stats)
            print(f"{k:>3d}{steps:>6d}{float(np.mean(leak > HIT)):>12.3f}{exact:>7d}  {cells}  {sec:.3f}",
                  flush=True)  # fmt: skip


def compare(ctx, k: int, draws: int) -> None:
    """The audit's k-shot rows against independent 16 x 200 code fits."""
    import torch

    from prop_cli.attack.probes import fewshot

    rows = {g.name: g for g in fewshot.run(ctx)}
    audit_rounded = float(rows[f"fewshot k={k} rounded"].values["leakage"].max())
    audit_fit = float(rows[f"fewshot k={k}"].values["bounded"].max())
    s = ctx.settings
    print(f"audit ({s.fewshot_restarts} x {s.fewshot_steps}), k = {k}: rounded code {audit_rounded:.3f}, "
          f"code and delta fit (bounded) {audit_fit:.3f}")  # fmt: skip
    user = ctx.codes(ctx.keys[0])
    shots = fewshot.shots_of(ctx, k)
    for d in range(draws):
        gen = torch.Generator().manual_seed(1000 + d)
        codes, loss = fewshot.fit_codes(ctx, shots, gen, 16, 200)
        pick = torch.where(codes[int(torch.argmin(loss))] >= 0, 1.0, -1.0)[None]
        leak = float(ctx.probe_codes(pick, "fewshot")["leakage"][0])
        dist = int((pick != user).sum())
        print(f"16 x 200 fit, draw {d + 1}: rounded code {leak:.3f}, code distance {dist}")


if __name__ == "__main__":
    main()
