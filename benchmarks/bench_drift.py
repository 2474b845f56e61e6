"""Does the no-key model stay the original? Drift on two tasks, with default settings.

    OMP_NUM_THREADS=1 python -m benchmarks.bench_drift reach3|digits-perm [--seeds 2] [--set KEY=JSON ...]
                                                       [--general]

- ``reach3``: the IL reach task in 3-D (pos' = pos + a) with a tanh MLP of 3 hidden layers of 160,
  behaviour-cloned from the expert; the user's key negates the action. Figures: personalization,
  no-key mse against the original (goal <= 1e-4; the base's own error against the expert is printed
  beside it), worst random / Hamming 1..8 key mse against the original.
- ``digits-perm``: scikit-learn's digits (offline), the user's labels a random permutation of the
  digit. Figures: personal accuracy, no-key agreement with the original, worst-key agreement over
  random and Hamming 1..8 keys (goal >= 0.99 for the mean of each group, reported with the worst).

Held-out test inputs throughout. ``--general`` also passes ``--general-data`` (inputs from the base's
training distribution); without it, the fallback inputs are what personalize gets by default.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from safetensors.torch import save_file
from torch import nn

from examples import fit, mlp, save_npz
from prop_cli.api import KeySource, personalize_checkpoint
from prop_cli.bundle import load_bundle
from prop_cli.config import PersonalizeConfig
from prop_cli.core.key_sampling import neighbours_at, random_keys
from prop_cli.core.keyed_model import key_codes, outputs_for_codes

RANDOM_KEYS = 256
PER_DISTANCE = 32
DISTANCES = range(1, 9)


def write_reach3(work: Path, seed: int) -> dict:
    from examples.il_task import expert_actions, make_states

    torch.manual_seed(seed)
    x_base = make_states(20000, seed * 1000, 3)
    y_base = torch.from_numpy(expert_actions(x_base, 3))
    model = mlp([6, 160, 160, 160, 3], nn.Tanh)
    fit(model, torch.from_numpy(x_base), y_base, nn.functional.mse_loss, steps=6000, batch=256, lr=1e-3,
        seed=seed, decay_at=0.7)  # fmt: skip
    save_file({k: v.contiguous() for k, v in model.state_dict().items()}, str(work / "base.safetensors"),
              metadata={"activation": "tanh"})  # fmt: skip
    x_mine = make_states(2000, seed * 1000 + 1, 3)
    x_test = make_states(2000, seed * 1000 + 3, 3)
    y_test = expert_actions(x_test, 3)
    return {
        "task": "regression",
        "model": model,
        "mine": save_npz(work / "mine.npz", x=x_mine, y=-expert_actions(x_mine, 3)),
        "general": save_npz(work / "general.npz", x=make_states(20000, seed * 1000 + 2, 3)),
        "x": x_test,
        "y": y_test,
        "y_personal": -y_test,
    }


def write_digits_perm(work: Path, seed: int) -> dict:
    from examples.digits_task import load_splits, make_mlp

    splits = load_splits(seed)
    perm = np.random.default_rng((seed, 77)).permutation(10)
    while (perm == np.arange(10)).any():  # every label moves
        perm = np.random.default_rng(int(perm.sum() + perm[0] * 10 + seed)).permutation(10)
    (xb, yb), (xu, yu), (xt, yt) = splits["base"], splits["user"], splits["test"]
    torch.manual_seed(seed)
    model = make_mlp()
    fit(model, torch.from_numpy(xb), torch.from_numpy(yb), nn.functional.cross_entropy, steps=600, batch=128,
        lr=1e-3, seed=seed, decay_at=0.7)  # fmt: skip
    save_file({k: v.contiguous() for k, v in model.state_dict().items()}, str(work / "base.safetensors"))
    return {
        "task": "classification",
        "model": model,
        "mine": save_npz(work / "mine.npz", x=xu, y=perm[yu].astype(np.int64)),
        "general": save_npz(work / "general.npz", x=xb),
        "x": xt,
        "y": yt,
        "y_personal": perm[yt].astype(np.int64),
    }


def run_seed(task: str, seed: int, work: Path, overrides: dict, general: bool) -> dict:
    work.mkdir(parents=True, exist_ok=True)
    t = write_reach3(work, seed) if task == "reach3" else write_digits_perm(work, seed)
    rng = np.random.default_rng((seed, 5))
    key = rng.integers(0, 2, 128, dtype=np.uint8)
    cfg = PersonalizeConfig.of(seed=seed, **overrides)
    t0 = time.perf_counter()
    personalize_checkpoint(
        str(work / "base.safetensors"), [(t["mine"], KeySource(key, "file"))], work / "b.prop", cfg,
        general=t["general"] if general else None, device="cpu", force=True,
    )  # fmt: skip
    seconds = time.perf_counter() - t0
    bundle = load_bundle(work / "b.prop")
    x = torch.from_numpy(t["x"])
    with torch.no_grad():
        b = t["model"](x)
        o_null = bundle.keyed(x)

    def probe(bits):
        return outputs_for_codes(bundle.keyed, x, key_codes(bits, bundle.key_encoding))

    o_user = probe(key)[0]
    others = {"random": probe(random_keys(RANDOM_KEYS, 128, rng, exclude=key))}
    others.update({f"h{d}": probe(neighbours_at(key, d, PER_DISTANCE, rng)) for d in DISTANCES})
    y, yp = torch.from_numpy(t["y"]), torch.from_numpy(t["y_personal"])
    row: dict = {"seed": seed, "seconds": round(seconds, 1)}
    if t["task"] == "regression":
        mse = lambda o, r: ((o - r) ** 2).flatten(-2).mean(-1)  # noqa: E731 - per key
        row["base_error"] = mse(b, y).item()
        row["personalization"] = 1 - mse(o_user, yp).item() / mse(b, yp).item()
        row["null_mse"] = mse(o_null, b).item()
        row["worst_key_mse"] = max(mse(o, b).max().item() for o in others.values())
        row["mean_key_mse"] = max(mse(o, b).mean().item() for o in others.values())
    else:
        agree = lambda o: (o.argmax(-1) == b.argmax(-1)).float().mean(-1)  # noqa: E731
        row["base_acc"] = (b.argmax(-1) == y).float().mean().item()
        row["personal_acc"] = (o_user.argmax(-1) == yp).float().mean().item()
        row["null_fidelity"] = agree(o_null).item()
        row["group_mean_fidelity_min"] = min(agree(o).mean().item() for o in others.values())
        row["worst_key_fidelity"] = min(agree(o).min().item() for o in others.values())
    return row


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("task", choices=["reach3", "digits-perm"])
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--general", action="store_true", help="also pass --general-data")
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=JSON", help="PersonalizeConfig overrides")
    args = ap.parse_args(argv)
    overrides = {k: json.loads(v) for k, v in (kv.split("=", 1) for kv in args.set)}
    with tempfile.TemporaryDirectory() as tmp:
        for seed in range(args.seeds):
            row = run_seed(args.task, seed, Path(tmp) / str(seed), overrides, args.general)
            print(json.dumps({k: (f"{v:.4g}" if isinstance(v, float) else v) for k, v in row.items()}),
                  flush=True)  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
