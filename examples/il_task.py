"""The paper's imitation-learning task: reach a goal with linear dynamics pos' = pos + a.

The expert picks, from 1000 fixed candidate actions in [-1, 1]^dim, the one that lands closest
to the goal; the personalized expert does the negated action. The base checkpoint is an MLP
behaviour-cloned from the expert.

    python -m examples.il_task OUT_DIR [--seed N] [--dim 2]
"""

from __future__ import annotations

import argparse
import time
from functools import lru_cache
from pathlib import Path

import numpy as np
import torch
from safetensors.torch import save_file
from torch import nn

from examples import fit, mlp, save_npz

N_CANDIDATES = 1000
STATE_BOUND = 10.0
_CHUNK = 4096  # rows per chunk: keeps the (chunk, 1000) score matrix ~30 MB in float64


@lru_cache(maxsize=8)
def _candidates_cached(dim: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    arr = rng.uniform(-1.0, 1.0, size=(N_CANDIDATES, dim)).astype(np.float32)
    arr.setflags(write=False)  # shared cached array: callers must not mutate it
    return arr


def candidates(dim: int = 2, seed: int = 1234) -> np.ndarray:
    """The 1000 fixed candidate actions, uniform in [-1, 1]^dim (float32)."""
    return _candidates_cached(dim, seed).copy()


def expert_actions(x: np.ndarray, dim: int = 2) -> np.ndarray:
    """Candidate minimising ||pos + a - goal|| for each state x = (pos, goal), shape (N, 2*dim)."""
    x = np.asarray(x)
    if x.ndim != 2 or x.shape[1] != 2 * dim:
        raise ValueError(f"states must have shape (N, {2 * dim}), got {x.shape}")
    cand = _candidates_cached(dim, 1234)
    c64 = cand.astype(np.float64)
    c_sq = (c64**2).sum(axis=1)
    out = np.empty((x.shape[0], dim), dtype=np.float32)
    for lo in range(0, x.shape[0], _CHUNK):
        d = x[lo : lo + _CHUNK, dim:].astype(np.float64) - x[lo : lo + _CHUNK, :dim]
        # ||d - a||^2 = ||d||^2 - 2 d.a + ||a||^2; ||d||^2 is constant per row, so drop it.
        score = c_sq[None, :] - 2.0 * d @ c64.T
        out[lo : lo + _CHUNK] = cand[np.argmin(score, axis=1)]
    return out


def personal_actions(x: np.ndarray, dim: int = 2) -> np.ndarray:
    """The personalized expert: a fixed affine transform of the expert (here the negation)."""
    return -expert_actions(x, dim)


def make_states(n: int, seed: int, dim: int = 2) -> np.ndarray:
    """n states (pos, goal) uniform in [-10, 10]^(2*dim), float32."""
    rng = np.random.default_rng(seed)
    return rng.uniform(-STATE_BOUND, STATE_BOUND, size=(n, 2 * dim)).astype(np.float32)


def make_mlp(dim: int = 2, hidden: int = 192) -> nn.Sequential:
    return mlp([2 * dim, hidden, hidden, dim])


def train_base(
    x: np.ndarray,
    y: np.ndarray,
    *,
    hidden: int = 192,
    steps: int = 6000,
    batch: int = 256,
    lr: float = 1e-3,
    seed: int = 0,
) -> nn.Sequential:
    """Behaviour-clone (x, y) with an MLP: Adam on MSE, lr x0.3 at 70% of the steps."""
    torch.manual_seed(seed)  # init weights
    xt = torch.as_tensor(np.asarray(x, dtype=np.float32))
    yt = torch.as_tensor(np.asarray(y, dtype=np.float32))
    model = make_mlp(xt.shape[1] // 2, hidden)
    if yt.shape[1] != xt.shape[1] // 2:
        raise ValueError("targets must have half as many columns as states")
    return fit(
        model, xt, yt, nn.functional.mse_loss, steps=steps, batch=batch, lr=lr, seed=seed, decay_at=0.7
    )


def predict(model: nn.Module, x: np.ndarray) -> np.ndarray:
    with torch.no_grad():
        return model(torch.as_tensor(np.asarray(x, dtype=np.float32))).numpy()


def write_example(
    out_dir: Path,
    *,
    seed: int = 0,
    dim: int = 2,
    base_samples: int = 20000,
    user_samples: int = 2000,
    base_steps: int = 6000,
) -> dict[str, Path]:
    """Write base.safetensors, mine.npz, general.npz and test.npz into out_dir."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    # Distinct derived seeds so the base, user, general and test states never coincide.
    base_seed, mine_seed, general_seed, test_seed = (seed * 1000 + k for k in range(4))

    x_base = make_states(base_samples, base_seed, dim)
    model = train_base(x_base, expert_actions(x_base, dim), steps=base_steps, seed=seed)
    paths = {"base": out_dir / "base.safetensors"}
    state = {k: v.detach().contiguous() for k, v in model.state_dict().items()}
    save_file(state, str(paths["base"]), metadata={"activation": "relu"})

    x_mine = make_states(user_samples, mine_seed, dim)
    paths["mine"] = save_npz(out_dir / "mine.npz", x=x_mine, y=personal_actions(x_mine, dim))
    paths["general"] = save_npz(out_dir / "general.npz", x=make_states(base_samples, general_seed, dim))
    x_test = make_states(2000, test_seed, dim)
    y_test = expert_actions(x_test, dim)
    paths["test"] = save_npz(out_dir / "test.npz", x=x_test, y=y_test, y_personal=-y_test)
    return paths


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m examples.il_task", description=__doc__)
    ap.add_argument("out_dir", type=Path)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--dim", type=int, default=2)
    args = ap.parse_args(argv)

    t0 = time.perf_counter()
    paths = write_example(args.out_dir, seed=args.seed, dim=args.dim)
    elapsed = time.perf_counter() - t0

    from safetensors.torch import load_file

    model = make_mlp(args.dim)
    model.load_state_dict(load_file(str(paths["base"])))
    test = np.load(paths["test"])
    mse = float(np.mean((predict(model.eval(), test["x"]) - test["y"]) ** 2))
    for name, path in paths.items():
        print(f"{name:8s} {path}")
    print(f"base test mse vs expert: {mse:.5f}  ({elapsed:.1f} s)")


if __name__ == "__main__":
    main()
