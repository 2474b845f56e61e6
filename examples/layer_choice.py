"""Which linear layers to key: personalization and leakage per layer choice, on the IL and digits examples.

    python -m examples.layer_choice [--seeds 1] [--tasks il digits] [--steps 2000]

For each task and seed it writes the example (base checkpoint, user data), then personalizes the same
base with each layer choice and default settings otherwise, through the library (``prop_cli.api``).
Printed per choice (means over seeds; metrics on the user's held-out validation split, as
``prop personalize`` reports them): personalization of the user's key, fidelity of random keys and of
the null key to the original, the leakage of the worst of 64 random keys, and the leakage of the user
key's 1-bit neighbours (mean and worst).
The choice ``prop_cli.core.layers.default_layers`` makes is the one this measurement supports.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from prop_cli.api import KeySource, personalize_checkpoint
from prop_cli.config import PersonalizeConfig, TrainConfig

# name -> which of the model's linear layers (in module order) it keys.
CHOICES = {
    "first": lambda n: n[:1],
    "last": lambda n: n[-1:],
    "all-but-first": lambda n: n[1:],
    "all-linear": lambda n: n[:-1],  # every layer but the output head
    "all": lambda n: list(n),
}


def _example(task: str, out: Path, seed: int) -> dict[str, Path]:
    if task == "il":
        from examples.il_task import write_example
    else:
        from examples.digits_task import write_example
    return write_example(out, seed=seed)


def _layer_names(base: Path) -> list[str]:
    import prop_adapters as adapters
    from prop_cli.core.layers import linear_layers

    return [n for n, _ in linear_layers(adapters.load_checkpoint(base).module)]


def run(task: str, seed: int, steps: int, work: Path) -> list[dict]:
    paths = _example(task, work / f"{task}-{seed}", seed)
    names = _layer_names(paths["base"])
    # A stream of its own: the trainer draws its evaluation keys from default_rng(seed + 10_000 + user).
    key = np.random.default_rng([seed, 0xC0FFEE]).integers(0, 2, 128, dtype=np.uint8)
    rows = []
    for choice, pick in CHOICES.items():
        cfg = PersonalizeConfig.of(steps=steps, seed=seed, layers=pick(names))
        t0 = time.perf_counter()
        res = personalize_checkpoint(
            str(paths["base"]),
            [(paths["mine"], KeySource(key, "file"))],
            work / f"{task}-{seed}-{choice}.prop",
            cfg,
            device="cpu",
        )
        m = res.metrics[0]
        rows.append(
            {
                "task": task,
                "seed": seed,
                "choice": choice,
                "layers": ",".join(pick(names)),
                "personalization": m["personalization"],
                "random_fidelity": m["random"]["fidelity"]["mean"],
                "random_leakage_worst": m["random"]["leakage"]["worst"],
                "null_fidelity": m["null"]["fidelity"]["mean"],
                "ham1_leakage": m["hamming1"]["leakage"]["mean"],
                "ham1_leakage_worst": m["hamming1"]["leakage"]["worst"],
                "seconds": time.perf_counter() - t0,
            }
        )
    return rows


COLUMNS = (
    ("personalization", "{:.4f}"),
    ("random_fidelity", "{:.3g}"),
    ("random_leakage_worst", "{:.4f}"),
    ("null_fidelity", "{:.3g}"),
    ("ham1_leakage", "{:.4f}"),
    ("ham1_leakage_worst", "{:.4f}"),
    ("seconds", "{:.1f}"),
)


def print_table(rows: list[dict]) -> None:
    print(
        "fidelity: mse to the original (il, lower is better) / agreement with it (digits, higher is better)"
    )
    head = f"{'task':6s} {'choice':14s} {'layers':18s} " + " ".join(f"{c:>21s}" for c, _ in COLUMNS)
    print(head)
    for task in dict.fromkeys(r["task"] for r in rows):
        for choice in CHOICES:
            sel = [r for r in rows if r["task"] == task and r["choice"] == choice]
            cells = " ".join(f"{fmt.format(np.mean([r[c] for r in sel])):>21s}" for c, fmt in COLUMNS)
            print(f"{task:6s} {choice:14s} {sel[0]['layers']:18s} {cells}")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m examples.layer_choice", description=__doc__)
    ap.add_argument("--seeds", type=int, default=1)
    ap.add_argument("--tasks", nargs="+", choices=("il", "digits"), default=["il", "digits"])
    ap.add_argument("--steps", type=int, default=TrainConfig().steps)
    args = ap.parse_args(argv)

    import torch

    torch.set_num_threads(1)
    rows: list[dict] = []
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="prop-layer-choice-") as tmp:
        for task in args.tasks:
            for seed in range(args.seeds):
                rows += run(task, seed, args.steps, Path(tmp))
    print_table(rows)
    print(f"({args.seeds} seed(s), {time.perf_counter() - t0:.0f} s in all)")


if __name__ == "__main__":
    main()
