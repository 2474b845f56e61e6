"""T1 relaxed search: how often it finds the user's code, against restarts, steps, lr and minibatch.

    python -m benchmarks.bench_relaxed_hits OUT_DIR [--tasks il digits] [--seed 0] [--pool 256]

Per task: the example with today's `prop personalize` defaults, then the audit's relaxed probe
(``prop_cli.attack.probes.relaxed``) run once per setting with ``--pool`` restarts. Restarts are independent
(per-restart loss, elementwise Adam), so the chance that the attacker's pick (the largest divergence)
among R restarts leaks > 0.5 is estimated from subsets of the pool. Prints one table; the audit's
defaults (docs/metrics.md, "T1 hit rate") were chosen from it.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np

SETTINGS = [  # (steps, lr, samples per step; 0 = all 256); the first is the audit's default
    (100, 0.1, 32),
    (100, 0.03, 32),
    (200, 0.1, 0),
    (50, 0.1, 32),
]
SIZES = (8, 16, 32, 64, 128, 256)
HIT = 0.5


def pick_hit(leak: np.ndarray, div: np.ndarray, r: int, draws: int = 2000, seed: int = 0) -> float:
    """P(the max-divergence restart among r leaks > HIT), over random r-subsets of the pool."""
    rng = np.random.default_rng(seed)
    sub = np.stack([rng.choice(len(leak), r, replace=False) for _ in range(draws)])
    pick = sub[np.arange(draws), np.argmax(div[sub], axis=1)]
    return float(np.mean(leak[pick] > HIT))


def bundle_for(task: str, out: Path, seed: int, key_stream: int) -> tuple[Path, Path, Path]:
    from prop_cli.api import KeySource, personalize_checkpoint
    from prop_cli.config import PersonalizeConfig

    if task == "il":
        from examples.il_task import write_example
    else:
        from examples.digits_task import write_example
    d = out / task
    paths = {"base": d / "base.safetensors", "mine": d / "mine.npz"}
    if not all(p.exists() for p in paths.values()):
        paths = write_example(d, seed=seed)
    key_path = d / "k.bin"
    if key_stream == 0:
        key = np.random.default_rng(10_000 + seed).integers(0, 256, 16, dtype=np.uint8).tobytes()
    else:  # the privacy study's keys (issue 9): bits from default_rng(50_000 + 97 * seed)
        bits = np.random.default_rng(50_000 + 97 * seed).integers(0, 2, 128, dtype=np.uint8)
        key = np.packbits(bits).tobytes()
    key_path.write_bytes(key)
    key_path.chmod(0o600)
    bundle = d / "mine.prop"
    if not bundle.exists():
        bits = np.unpackbits(np.frombuffer(key, np.uint8))
        personalize_checkpoint(
            str(paths["base"]),
            [(paths["mine"], KeySource(bits, "file"))],
            bundle,
            PersonalizeConfig.of(seed=seed),
        )
    return bundle, paths["mine"], key_path


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.bench_relaxed_hits", description=__doc__)
    ap.add_argument("out_dir", type=Path)
    ap.add_argument("--tasks", nargs="+", default=["il", "digits"])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--pool", type=int, default=256)
    ap.add_argument(
        "--settings", default=None, help="indices into SETTINGS to run, e.g. 0 (the default) or 0,1,3"
    )
    ap.add_argument("--key-stream", type=int, default=0, choices=[0, 1], help="1: the privacy study's keys")
    args = ap.parse_args(argv)
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    import torch

    torch.set_num_threads(1)
    from prop_cli.api import audit_bundle
    from prop_cli.config import AuditSettings

    rows = []
    for task in args.tasks:
        bundle, mine, key = bundle_for(task, args.out_dir, args.seed, args.key_stream)
        chosen = SETTINGS if args.settings is None else [SETTINGS[int(i)] for i in args.settings.split(",")]
        for steps, lr, batch in chosen:
            s = AuditSettings(probes=["relaxed"], restarts=args.pool, search_steps=steps, search_lr=lr,
                              search_batch=batch, seed=args.seed)  # fmt: skip
            t0 = time.perf_counter()
            rep = audit_bundle(bundle, mine, s, key_files=[key])
            sec = time.perf_counter() - t0
            for g in rep["groups"]:
                srch = g["search"]
                leak, div = np.array(srch["leakage"]), np.array(srch["divergence"])
                hits = [pick_hit(leak, div, r) if r < len(leak) else float(leak[np.argmax(div)] > HIT)
                        for r in SIZES if r <= len(leak)]  # fmt: skip
                rows.append((task, g["name"], steps, lr, batch, float(np.mean(leak > HIT)), hits,
                             sec / args.pool))  # fmt: skip
    head = " ".join(f"R={r:<4d}" for r in SIZES)
    print(
        f"T1 attacker's-pick hit rate (leakage > {HIT}) from a pool of {args.pool} restarts; seed {args.seed}"
    )
    print(
        f"{'task':7s}{'group':17s}{'steps':>6s}{'lr':>6s}{'batch':>6s}{'per-restart':>12s}  {head}  s/restart"
    )
    for task, name, steps, lr, batch, per, hits, spr in rows:
        cells = " ".join(f"{h:<6.2f}" for h in hits)
        print(f"{task:7s}{name:17s}{steps:>6d}{lr:>6g}{batch:>6d}{per:>12.3f}  {cells}  {spr:.3f}")


if __name__ == "__main__":
    main()
