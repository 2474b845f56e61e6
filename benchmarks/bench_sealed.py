"""What sealing costs: personalization of sealed bundles against unsealed PRoP, on IL and digits.

    python -m benchmarks.bench_sealed [--seeds 2] [--tasks il,digits] [--quick]

Per task and seed: the example is written (base checkpoint trained from scratch, the user's data, a
fresh key), then personalized through the library with default settings, unsealed (the paper's PRoP)
and sealed with each payload kind. Scored on the held-out test set: personalization (regression:
1 - mse(o, p) / mse(b, p); classification: accuracy on the personalized labels), the payload's size,
training wall time, and the wrong keys (null, 64 random, every 1-bit neighbour of the user's key) run
through the bundle as a user runs them: for sealed bundles, the share whose output is bit-identical
to the no-key output. Reach (PPO) has its own script: benchmarks/bench_sealed_reach.py.
"""

from __future__ import annotations

import argparse
import time
import warnings

import numpy as np
import torch

from examples import task_runs
from prop_cli.api import KeySource, personalize_checkpoint
from prop_cli.bundle import load_bundle
from prop_cli.config import PersonalizeConfig
from prop_cli.core.key_sampling import one_bit_neighbours, random_keys
from prop_cli.core.metrics import personalization
from prop_cli.run.policy import KeyedPolicy, WrongKeyWarning

VARIANTS = {
    "unsealed (PRoP)": {},
    "sealed lora r4": {"seal": True, "payload": "lora", "payload_rank": 4},
    "sealed delta": {"seal": True, "payload": "delta"},
    "sealed full": {"seal": True, "payload": "full", "payload_lr": 0.003},
}


def _score(bundle, bits: np.ndarray, test: dict, task: str) -> dict:
    x = test["x"]
    b = KeyedPolicy(bundle, None)(x)
    o = KeyedPolicy(bundle, bits)(x)
    p = test["y_personal"]
    kind = "classification" if task == "digits" else "regression"
    tp = torch.from_numpy(p if kind == "classification" else p.astype(np.float32))
    pers = personalization(torch.from_numpy(o), tp, torch.from_numpy(b), kind)
    rng = np.random.default_rng(7)
    wrong = [*random_keys(64, len(bits), rng, exclude=bits), *one_bit_neighbours(bits)]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", WrongKeyWarning)
        outs = [KeyedPolicy(bundle, k, allow_unenrolled=True)(x) for k in wrong]
    identical = float(np.mean([np.array_equal(w, b) for w in outs]))
    if kind == "classification":
        moved = float(max((w.argmax(-1) != b.argmax(-1)).mean() for w in outs))
    else:
        moved = float(max(((w - b) ** 2).mean() for w in outs))
    return {"personalization": pers, "wrong_keys_identical": identical, "wrong_keys_worst_change": moved}


def run(tasks: list[str], seeds: int, quick: bool) -> list[dict]:
    rows = []
    for task, seed, work, paths, bits in task_runs(tasks, seeds, "prop-sealed-", 1000):
        test = dict(np.load(paths["test"]))
        for name, over in VARIANTS.items():
            cfg = PersonalizeConfig.of(seed=seed, **over)
            if quick:
                cfg = cfg.replace(steps=300)
            t0 = time.perf_counter()
            out = work / f"{len(rows)}.prop"
            personalize_checkpoint(
                str(paths["base"]), [(paths["mine"], KeySource(bits, "file"))], out, cfg, device="cpu"
            )
            seconds = time.perf_counter() - t0
            bundle = load_bundle(out)
            size = sum(f.stat().st_size for f in out.rglob("*") if f.is_file() and "users" in f.parts)
            if not bundle.is_sealed:
                size = (out / "encoder.safetensors").stat().st_size
            rows.append(
                {
                    "task": task,
                    "seed": seed,
                    "variant": name,
                    "seconds": seconds,
                    "user_bytes": size,
                    **_score(bundle, bits, test, task),
                }  # fmt: skip
            )
            r = rows[-1]
            print(
                f"{task:6s} seed {seed} {name:16s} personalization {r['personalization']:.4f}  "
                f"wrong keys identical {r['wrong_keys_identical']:.3f}  worst change "
                f"{r['wrong_keys_worst_change']:.3g}  {r['user_bytes']} B  {seconds:.1f} s",
                flush=True,
            )
    return rows


def table(rows: list[dict]) -> str:
    lines = [
        "| task | variant | personalization (mean over seeds) | vs unsealed "
        "| wrong keys bit-identical to no key "
        "| per-user bytes | train s |",
        "|---|---|---|---|---|---|---|",
    ]
    for task in dict.fromkeys(r["task"] for r in rows):
        ref = np.mean(
            [r["personalization"] for r in rows if r["task"] == task and r["variant"] == "unsealed (PRoP)"]
        )
        for name in VARIANTS:
            sel = [r for r in rows if r["task"] == task and r["variant"] == name]
            if not sel:
                continue
            pers = np.mean([r["personalization"] for r in sel])
            lines.append(
                f"| {task} | {name} | {pers:.4f} | {100 * (pers - ref) / abs(ref):+.1f}% "
                f"| {np.mean([r['wrong_keys_identical'] for r in sel]):.3f} "
                f"| {int(np.mean([r['user_bytes'] for r in sel]))} "
                f"| {np.mean([r['seconds'] for r in sel]):.1f} |"
            )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--tasks", default="il,digits")
    ap.add_argument("--quick", action="store_true", help="300 steps, for a smoke run")
    a = ap.parse_args(argv)
    torch.set_num_threads(1)
    rows = run(a.tasks.split(","), a.seeds, a.quick)
    print()
    print(table(rows))


if __name__ == "__main__":
    main()
