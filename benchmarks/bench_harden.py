"""Default vs hardened (`prop personalize --harden`) on IL, digits and reach: every attack, with controls.

    OMP_NUM_THREADS=1 python -m benchmarks.bench_harden [--quick] [--tasks il digits reach]
        [--seeds 0 1] [--keys 1000000] [--json out.json] [--workdir DIR]

Per task, seed and mode: training seconds, personalization and no-key fidelity on held-out samples;
then, as an attacker holding the bundle would (benchmarks/harden_attacks.py): Hamming 1..8 neighbours
of the user's key (128 per distance, worst), --keys random keys (streamed, worst after re-scoring),
T1 relaxed search with 64 restarts at lr 0.1 and 1.0 (the attacker's pick, its control, and the
pick beyond control), structure attacks (best pick; control), few-shot
T3 with k = 1, 4, 16, 64 samples (code fit, delta fit; control: fine-tuning the original).
The searches' control is the same attack on a bundle trained the same way (same mode, key and
seed) on the user's inputs labelled by the original: it holds nothing of the user. (The bundle's
encoder on the original checkpoint is no control: the encoder carries the personalization.)
Leakage is prop_cli.core.metrics.leakage on 256 held-out samples. --quick: IL, seed 0, 200 steps, 16k
keys, few-shot k = 1, 4 (a smoke run, not a measurement). Goals (issue 9): hardened T1-64 beyond
control <= 0.05, 1M random keys worst <= 0.05, Hamming 1..8 no worse than default.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks import harden_attacks as A

TASKS = ("il", "digits", "reach")
MODES = {"default": {}, "hardened": {"harden": True}}
EVAL_SAMPLES = 256


def write_task(name: str, out: Path, seed: int) -> None:
    if (out / "test.npz").exists():
        return
    if name == "il":
        from examples.il_task import write_example
    elif name == "digits":
        from examples.digits_task import write_example
    else:
        from examples.reach_task import write_example
    write_example(out, seed=seed)


def user_key(seed: int) -> np.ndarray:
    return np.random.default_rng(50_000 + 97 * seed).integers(0, 2, 128, dtype=np.uint8)


def train(base: Path, data, key: np.ndarray, cfg) -> tuple:
    """`prop personalize` in memory: (keyed model, original, task, wall seconds)."""
    import prop_adapters as adapters
    from prop_cli.train import User, personalize

    t0 = time.perf_counter()
    res = personalize(adapters.load_checkpoint(str(base)), [User(data, key)], cfg)
    seconds = time.perf_counter() - t0
    return (
        res.keyed.eval().requires_grad_(False),
        res.original.eval().requires_grad_(False),
        res.task,
        seconds,
    )


def null_data(data, original: torch.nn.Module, task: str):
    """The user's inputs labelled by the original itself: a bundle trained on them holds nothing of
    the user, so what an attack finds on it is the control for the real bundle."""
    from prop_cli.datasources import Dataset

    with torch.no_grad():
        o = original(torch.from_numpy(data.x)).numpy()
    y = o.argmax(-1).astype(np.int64) if task == "classification" else o.reshape(data.y.shape)
    return Dataset(data.x, y, "<original's outputs>")


def run_case(task: str, seed: int, mode: str, args) -> dict:
    from prop_cli.config import PersonalizeConfig
    from prop_cli.core import metrics
    from prop_cli.core.keyed_model import key_codes
    from prop_cli.datasources import load_data

    d = args.workdir / f"{task}_s{seed}"
    write_task(task, d, seed)
    mine = load_data(d / "mine.npz")
    key = user_key(seed)

    def config() -> PersonalizeConfig:
        return PersonalizeConfig.of(seed=seed, steps=args.steps, **MODES[mode])

    cfg = config()
    km, original, kind, train_s = train(d / "base.safetensors", mine, key, cfg)
    ctrl = train(d / "base.safetensors", null_data(mine, original, kind), key, config())[0]

    test = np.load(d / "test.npz")
    x = torch.from_numpy(test["x"][:EVAL_SAMPLES])
    p = torch.from_numpy(test["y_personal"][:EVAL_SAMPLES])
    with torch.no_grad():
        b = original(x)
        null = km(x)
        own = km.run_keys(x, km.layer_deltas(key_codes(key, cfg.mode.key_encoding)))[0]
    ref = A.Ref(x, b, p, kind)
    t0 = time.perf_counter()
    t1_bundle = A.t1(km, ref, args.restarts, args.search_steps)
    t1_ctrl = A.t1(ctrl, ref, args.restarts, args.search_steps)
    y = torch.from_numpy(mine.y)
    if kind == "regression" and y.dim() == 1:
        y = y[:, None]
    row = {
        "task": task,
        "seed": seed,
        "mode": mode,
        "train_seconds": train_s,
        "personalization": metrics.personalization(own, p, b, kind),
        "fidelity_null": float(metrics.fidelity(null[None], b, kind)[0]),
        "hamming": A.hamming_worst(km, ref, key, cfg.mode.key_encoding),
        "random": A.random_scan(km, ref, args.keys, cfg.mode.key_encoding),
        "t1": {
            "bundle": t1_bundle,
            "control": t1_ctrl,
            "beyond": max(0.0, t1_bundle["pick"] - t1_ctrl["pick"]),
        },
        "structure": {
            "bundle": A.structure(km, ref, cfg.train.seed), "control": A.structure(ctrl, ref, cfg.train.seed)
        },
        "fewshot": A.fewshot(km, original, ref, torch.from_numpy(mine.x), y, args.fewshot),
    }
    row["hamming_worst"] = max(row["hamming"].values())
    row["attack_seconds"] = time.perf_counter() - t0
    return row


def print_tables(rows: list[dict], ks: list[int]) -> None:
    print("\nPrivacy (leakage, 0..1; T1 = attacker's pick of 64 restarts; structure = best attack's pick;")
    print("ctrl = the same attack on a bundle trained on the original's own outputs)")
    cols = [("train s", 8), ("pers", 7), ("fid0", 8), ("ham1-8", 8), ("rand worst", 11), ("keys", 9),
            ("T1", 7), ("ctrl", 7), ("beyond", 7), ("struct", 8), ("ctrl", 7)]  # fmt: skip
    print(f"{'task':7}{'seed':>5} {'mode':9}" + "".join(f"{c:>{w}}" for c, w in cols))
    for r in rows:
        print(
            f"{r['task']:7}{r['seed']:>5} {r['mode']:9}{r['train_seconds']:8.1f}{r['personalization']:7.3f}"
            f"{r['fidelity_null']:8.4f}{r['hamming_worst']:8.3f}{r['random']['worst']:11.3f}"
            f"{r['random']['keys']:>9}{r['t1']['bundle']['pick']:7.3f}{r['t1']['control']['pick']:7.3f}"
            f"{r['t1']['beyond']:7.3f}{max(r['structure']['bundle'].values()):8.3f}"
            f"{max(r['structure']['control'].values()):7.3f}"
        )
    print("\nFew-shot T3 (leakage after fitting k of the user's samples: code | delta | control fine-tune)")
    print(f"{'task':7}{'seed':>5} {'mode':9}" + "".join(f"{'k=' + str(k):>20}" for k in ks))
    for r in rows:
        cells = "".join(
            f"{f['code']:8.2f}{f['delta']:6.2f}{f['control']:6.2f}" for f in (r["fewshot"][k] for k in ks)
        )
        print(f"{r['task']:7}{r['seed']:>5} {r['mode']:9}" + cells)
    print("\nTraining time, hardened / default (same run):")
    for task in dict.fromkeys(r["task"] for r in rows):
        for seed in dict.fromkeys(r["seed"] for r in rows):
            t = {r["mode"]: r["train_seconds"] for r in rows if r["task"] == task and r["seed"] == seed}
            if len(t) == 2:
                print(f"  {task} seed {seed}: {t['hardened'] / t['default']:.2f}x")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.bench_harden", description=__doc__)
    ap.add_argument("--quick", action="store_true", help="Smoke run: IL, seed 0, small budgets.")
    ap.add_argument("--tasks", nargs="+", choices=TASKS, default=list(TASKS))
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    ap.add_argument("--modes", nargs="+", choices=list(MODES), default=list(MODES))
    ap.add_argument("--keys", type=int, default=None, help="Random keys to scan (default 1,000,000).")
    ap.add_argument("--steps", type=int, default=None, help="Training steps (default: the config's).")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--workdir", type=Path, default=None)
    args = ap.parse_args(argv)
    from prop_cli.config import TrainConfig

    args.restarts, args.search_steps, args.fewshot = 64, 200, [1, 4, 16, 64]
    if args.quick:
        args.tasks, args.seeds = ["il"], [0]
        args.keys, args.steps = args.keys or 16_384, args.steps or 200
        args.restarts, args.search_steps, args.fewshot = 8, 20, [1, 4]
    args.keys = args.keys or 1_000_000
    args.steps = args.steps or TrainConfig().steps
    torch.set_flush_denormal(True)
    with tempfile.TemporaryDirectory() as tmp:
        args.workdir = args.workdir or Path(tmp)
        rows = []
        for task in args.tasks:
            for seed in args.seeds:
                for mode in args.modes:
                    rows.append(run_case(task, seed, mode, args))
                    r = rows[-1]
                    print(f"[{task} s{seed} {mode}] train {r['train_seconds']:.0f} s, attacks "
                          f"{r['attack_seconds']:.0f} s", flush=True)  # fmt: skip
                    if args.json:
                        args.json.write_text(json.dumps(rows, indent=2, sort_keys=True) + "\n")
    print_tables(rows, args.fewshot)


if __name__ == "__main__":
    main()
