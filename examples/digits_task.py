"""Classification on scikit-learn's bundled digits (offline): personalize to offset labels.

The user's labels are the true digit shifted by OFFSET (mod 10). The base checkpoint is an
MLP whose state-dict keys carry a "net." prefix, to exercise prefix handling downstream.

    python -m examples.digits_task OUT_DIR [--seed N]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch
from safetensors.torch import save_file
from torch import nn

from examples import fit, mlp, save_npz

OFFSET = 3
N_CLASSES = 10
PREFIX = "net."


def personal_labels(y: np.ndarray) -> np.ndarray:
    return ((np.asarray(y, dtype=np.int64) + OFFSET) % N_CLASSES).astype(np.int64)


def load_splits(seed: int = 0) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Deterministic 60/20/20 split into base-train, user and test: name -> (x, y true labels)."""
    from sklearn.datasets import load_digits  # ships with sklearn, no download

    digits = load_digits()
    x = (digits.data / 16.0).astype(np.float32)  # pixel counts 0..16 -> [0, 1]
    y = digits.target.astype(np.int64)
    perm = np.random.default_rng(seed).permutation(len(x))
    n_base, n_user = int(0.6 * len(x)), int(0.2 * len(x))
    parts = {
        "base": perm[:n_base],
        "user": perm[n_base : n_base + n_user],
        "test": perm[n_base + n_user :],
    }
    return {name: (x[idx], y[idx]) for name, idx in parts.items()}


def make_mlp(hidden: int = 128) -> nn.Sequential:
    return mlp([64, hidden, hidden, N_CLASSES])


def train_base(
    x: np.ndarray, y: np.ndarray, *, hidden: int = 128, steps: int = 600, batch: int = 128, lr: float = 1e-3,
    seed: int = 0,
) -> nn.Sequential:  # fmt: skip
    """Adam on cross-entropy with minibatches drawn from a seeded generator (repeatable)."""
    torch.manual_seed(seed)
    xt = torch.as_tensor(np.asarray(x, dtype=np.float32))
    yt = torch.as_tensor(np.asarray(y, dtype=np.int64))
    model = make_mlp(hidden)
    return fit(model, xt, yt, nn.functional.cross_entropy, steps=steps, batch=batch, lr=lr, seed=seed)


def accuracy(model: nn.Module, x: np.ndarray, y: np.ndarray) -> float:
    with torch.no_grad():
        pred = model(torch.as_tensor(np.asarray(x, dtype=np.float32))).argmax(dim=1).numpy()
    return float(np.mean(pred == np.asarray(y)))


def write_example(out_dir: Path, *, seed: int = 0) -> dict[str, Path]:
    """Write base.safetensors, mine.npz, general.npz and test.npz into out_dir."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    splits = load_splits(seed)
    x_base, y_base = splits["base"]
    x_user, y_user = splits["user"]
    x_test, y_test = splits["test"]

    model = train_base(x_base, y_base, seed=seed)
    paths = {"base": out_dir / "base.safetensors"}
    state = {PREFIX + k: v.detach().contiguous() for k, v in model.state_dict().items()}
    save_file(state, str(paths["base"]), metadata={"activation": "relu"})
    paths["mine"] = save_npz(out_dir / "mine.npz", x=x_user, y=personal_labels(y_user))
    paths["general"] = save_npz(out_dir / "general.npz", x=x_base)
    paths["test"] = save_npz(out_dir / "test.npz", x=x_test, y=y_test, y_personal=personal_labels(y_test))
    return paths


def load_base(path: Path) -> nn.Sequential:
    """Rebuild the base MLP from a checkpoint written by write_example (strips the prefix)."""
    from safetensors.torch import load_file

    state = load_file(str(path))
    model = make_mlp(state[PREFIX + "0.weight"].shape[0])
    model.load_state_dict({k.removeprefix(PREFIX): v for k, v in state.items()})
    return model.eval()


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m examples.digits_task", description=__doc__)
    ap.add_argument("out_dir", type=Path)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)

    t0 = time.perf_counter()
    paths = write_example(args.out_dir, seed=args.seed)
    elapsed = time.perf_counter() - t0
    test = np.load(paths["test"])
    acc = accuracy(load_base(paths["base"]), test["x"], test["y"])
    for name, path in paths.items():
        print(f"{name:8s} {path}")
    print(f"base test accuracy: {acc:.4f}  ({elapsed:.1f} s)")


if __name__ == "__main__":
    main()
