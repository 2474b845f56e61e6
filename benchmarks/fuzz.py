"""Fuzz every input kind prop reads and print the outcomes (issue 14's figures).

For each kind (bundle, checkpoint: safetensors and torch .pt, npz, SB3 zip) runs N seeded cases
(default 10,000) of tests/fuzzing.py's mutations and prints counts by seed, mutation and outcome.
Goal: 0 ``crash:*`` outcomes anywhere, and no damaged bundle (any corruption mutation) that loads.
``changed`` under a corruption is expected only for safetensors checkpoints (no checksum in the format).

    OMP_NUM_THREADS=1 python -m benchmarks.fuzz [--cases 10000] [--seed 0] [--kinds bundle,npz]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

import torch

from tests.bundle.fuzzing import KINDS, MUTATIONS, fuzz, make_seeds


def _table(counts: Counter) -> list[str]:
    outcomes = sorted({o for _, _, o in counts})
    names = sorted({n for n, _, _ in counts})
    lines = [f"{'seed':<18} {'mutation':<9} " + " ".join(f"{o:>8}" for o in outcomes)]
    for name in names:
        for how in MUTATIONS:
            row = [counts.get((name, how, o), 0) for o in outcomes]
            if sum(row):
                lines.append(f"{name:<18} {how:<9} " + " ".join(f"{v:>8}" for v in row))
        total = [sum(v for (n, _, o), v in counts.items() if n == name and o == oc) for oc in outcomes]
        lines.append(f"{name:<18} {'all':<9} " + " ".join(f"{v:>8}" for v in total))
    return lines


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=10_000, help="cases per input kind")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--kinds", default=",".join(KINDS))
    args = ap.parse_args()
    torch.set_num_threads(1)
    failures = 0
    with tempfile.TemporaryDirectory() as d:
        work = Path(d)
        seeds = make_seeds(work / "seeds")
        for kind in args.kinds.split(","):
            t0 = time.perf_counter()
            counts, bad = fuzz(seeds[kind], args.cases, work / "case", seed=args.seed)
            took = time.perf_counter() - t0
            crashes = sum(v for (_, _, o), v in counts.items() if o.startswith("crash"))
            head = f"{kind}: {args.cases} cases in {took:.1f} s; crashes {crashes}; disallowed {len(bad)}"
            print(f"\n== {head}")
            print("\n".join(_table(counts)))
            for case in bad[:20]:
                print("   disallowed:", case)
            failures += len(bad)
    print(f"\nverdict: {'PASS' if failures == 0 else 'FAIL'} ({failures} disallowed outcomes)")
    return 0 if failures == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
