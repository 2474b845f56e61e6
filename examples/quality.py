"""The core issue's quality bars, measured: IL (dim 2) over seeds, and digits with a label offset.

    python -m examples.quality il [--seeds 5]       # personalized mse, random / Hamming 1..8 / null
    python -m examples.quality digits [--seeds 5]   # accuracy vs base, fidelity of other keys

Each seed writes its own example (base checkpoint trained from scratch, user data, a fresh key),
personalizes with default settings through the library (`prop_cli.api`), then evaluates on a held-out
test set. Prints one row per seed and whether every bar holds.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from prop_cli.api import KeySource, personalize_checkpoint
from prop_cli.bundle import load_bundle
from prop_cli.config import PersonalizeConfig
from prop_cli.core.key_sampling import neighbours_at, random_keys
from prop_cli.core.keyed_model import key_codes, outputs_for_codes

DISTANCES = range(1, 9)
KEYS_PER_DISTANCE = 64
RANDOM_KEYS = 256


def _probe(bundle, x: torch.Tensor, bits: np.ndarray) -> torch.Tensor:
    return outputs_for_codes(bundle.keyed, x, key_codes(bits, bundle.key_encoding))


def run_seed(task: str, seed: int, work: Path, overrides: dict | None = None) -> dict:
    if task == "il":
        from examples.il_task import write_example
    else:
        from examples.digits_task import write_example
    paths = write_example(work / f"{task}-{seed}", seed=seed)
    rng = np.random.default_rng((seed, 2))
    key = rng.integers(0, 2, 128, dtype=np.uint8)  # stands in for `prop keygen`; seeded so reruns match
    t0 = time.perf_counter()
    personalize_checkpoint(
        str(paths["base"]),
        [(paths["mine"], KeySource(key, "file"))],
        work / f"{task}-{seed}.prop",
        PersonalizeConfig.of(seed=seed, **(overrides or {})),
        general=paths["general"],
        device="cpu",
    )
    seconds = time.perf_counter() - t0
    bundle = load_bundle(work / f"{task}-{seed}.prop")
    test = np.load(paths["test"])
    x = torch.from_numpy(test["x"])
    y, yp = torch.from_numpy(test["y"]), torch.from_numpy(test["y_personal"])
    with torch.no_grad():
        from prop_adapters import load_checkpoint

        b = load_checkpoint(str(paths["base"])).module(x)
        o_null = bundle.keyed(x)
    o_user = _probe(bundle, x, key)[0]
    o_rand = _probe(bundle, x, random_keys(RANDOM_KEYS, 128, rng, exclude=key))
    o_ham = {d: _probe(bundle, x, neighbours_at(key, d, KEYS_PER_DISTANCE, rng)) for d in DISTANCES}
    row: dict = {"seed": seed, "seconds": seconds}
    if task == "il":
        mse = lambda o, t: ((o - t) ** 2).flatten(-2).mean(-1)  # noqa: E731 - per key
        row["base_mse"] = mse(b, y).item()
        row["personal_mse"] = mse(o_user, yp).item()
        row["null_vs_original"] = mse(o_null, b).item()
        row["random_mse"] = mse(o_rand, y).mean().item()
        row["random_worst"] = mse(o_rand, y).max().item()
        row["hamming_mse"] = {d: mse(o, y).mean().item() for d, o in o_ham.items()}
        row["hamming_worst"] = {d: mse(o, y).max().item() for d, o in o_ham.items()}
    else:
        acc = lambda o, t: (o.argmax(-1) == t).float().mean(-1)  # noqa: E731
        agree = lambda o: (o.argmax(-1) == b.argmax(-1)).float().mean(-1)  # noqa: E731
        row["base_acc"] = acc(b, y).item()
        row["personal_acc"] = acc(o_user, yp).item()
        row["null_fidelity"] = agree(o_null).item()
        row["random_fidelity"] = agree(o_rand).mean().item()
        row["random_worst"] = agree(o_rand).min().item()
        row["hamming_fidelity"] = {d: agree(o).mean().item() for d, o in o_ham.items()}
        row["hamming_worst"] = {d: agree(o).min().item() for d, o in o_ham.items()}
    return row


def check(task: str, row: dict) -> list[str]:
    """The bars from the core issue; returns the ones missed."""
    missed = []
    if task == "il":
        if row["personal_mse"] > 0.02:
            missed.append("personal_mse > 0.02")
        if row["random_mse"] > 0.01:
            missed.append("random_mse > 0.01")
        missed += [f"hamming{d} > 0.01" for d, v in row["hamming_mse"].items() if v > 0.01]
        if row["null_vs_original"] > 1e-4:
            missed.append("null_vs_original > 1e-4")
    else:
        if row["personal_acc"] < row["base_acc"] - 0.01:
            missed.append("personal_acc < base_acc - 1pt")
        if row["random_fidelity"] < 0.99:
            missed.append("random_fidelity < 0.99")
        missed += [f"hamming{d} < 0.99" for d, v in row["hamming_fidelity"].items() if v < 0.99]
    return missed


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("task", choices=["il", "digits"])
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=JSON", help="PersonalizeConfig overrides")
    args = ap.parse_args(argv)
    overrides = {k: json.loads(v) for k, v in (kv.split("=", 1) for kv in args.set)}
    failures = 0
    with tempfile.TemporaryDirectory() as tmp:
        for seed in range(args.seeds):
            row = run_seed(args.task, seed, Path(tmp), overrides)
            missed = check(args.task, row)
            failures += bool(missed)
            if args.task == "il":
                ham = " ".join(f"{v:.4f}" for v in row["hamming_mse"].values())
                print(
                    f"seed {seed}: personalize {row['seconds']:.1f}s | base mse {row['base_mse']:.4f} | "
                    f"personal mse {row['personal_mse']:.4f} | null vs original {row['null_vs_original']:.2e}"
                    f" | random mse {row['random_mse']:.4f} (worst key {row['random_worst']:.4f})"
                    f" | hamming 1..8 mse {ham} (worst key {max(row['hamming_worst'].values()):.4f})"
                    f" | {'OK' if not missed else 'MISSED: ' + ', '.join(missed)}"
                )
            else:
                ham = " ".join(f"{v:.3f}" for v in row["hamming_fidelity"].values())
                print(
                    f"seed {seed}: personalize {row['seconds']:.1f}s | base acc {row['base_acc']:.3f} | "
                    f"personal acc {row['personal_acc']:.3f} | null fidelity {row['null_fidelity']:.3f} | "
                    f"random fidelity {row['random_fidelity']:.3f} (worst key {row['random_worst']:.3f}) | "
                    f"hamming 1..8 fidelity {ham} (worst key {min(row['hamming_worst'].values()):.3f})"
                    f" | {'OK' if not missed else 'MISSED: ' + ', '.join(missed)}"
                )
    print(f"{args.seeds - failures}/{args.seeds} seeds meet every bar")
    return 1 if failures else 0


if __name__ == "__main__":
    raise SystemExit(main())
