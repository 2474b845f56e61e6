"""A quick, supervised stand-in for the paper's reach task (examples/reproduce/reach.py needs
panda-gym and PPO; this needs neither): a 7-joint arm's action towards a goal.

State (9 numbers): end-effector position, its velocity and the goal, in the reach task's goal box.
Expert action (7 joint deltas): a fixed random 3x7 Jacobian's pseudo-inverse applied to a
proportional-derivative pull towards the goal, clipped to [-1, 1]. The personalized expert pulls
towards A g + c instead, the affine goal map of examples/reproduce/reach.py (a 90-degree turn about
the vertical axis, z mirrored inside the box). The base checkpoint is an MLP behaviour-cloned from
the expert.

    python -m examples.reach_task OUT_DIR [--seed N]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch
from safetensors.torch import save_file
from torch import nn

from examples import fit, mlp, save_npz

JOINTS = 7
GAIN = 8.0
DAMPING = 2.0
_JACOBIAN_SEED = 1234


def goal_transform(g: np.ndarray) -> np.ndarray:
    """A g + c on (N, 3) goals: (x, y, z) -> (-y, x, 0.3 - z), the goal box onto itself."""
    return np.stack([-g[:, 1], g[:, 0], 0.3 - g[:, 2]], axis=1).astype(np.float32)


def _pinv_jacobian() -> np.ndarray:
    j = np.random.default_rng(_JACOBIAN_SEED).standard_normal((3, JOINTS)) / np.sqrt(JOINTS)
    return np.linalg.pinv(j).astype(np.float32)  # (7, 3)


def actions(x: np.ndarray, goal: np.ndarray) -> np.ndarray:
    """Joint deltas pulling the end effector at x[:, :3] (velocity x[:, 3:6]) towards ``goal``."""
    pull = GAIN * (goal - x[:, :3]) - DAMPING * x[:, 3:6]
    return np.clip(pull @ _pinv_jacobian().T, -1.0, 1.0).astype(np.float32)


def expert_actions(x: np.ndarray) -> np.ndarray:
    return actions(x, x[:, 6:9])


def personal_actions(x: np.ndarray) -> np.ndarray:
    return actions(x, goal_transform(x[:, 6:9]))


def make_states(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    box = np.array([[-0.15, -0.15, 0.0], [0.15, 0.15, 0.3]], np.float32)

    def in_box(k: int) -> np.ndarray:
        return rng.uniform(box[0], box[1], (k, 3))

    return np.concatenate([in_box(n), rng.normal(0, 0.05, (n, 3)), in_box(n)], axis=1).astype(np.float32)


def write_example(out_dir: Path, *, seed: int = 0, base_steps: int = 4000) -> dict[str, Path]:
    """Write base.safetensors, mine.npz, general.npz and test.npz into out_dir."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    base_seed, mine_seed, general_seed, test_seed = (seed * 1000 + 500 + k for k in range(4))
    x_base = make_states(20000, base_seed)
    torch.manual_seed(seed)
    model = fit(
        mlp([9, 128, 128, JOINTS]), torch.from_numpy(x_base), torch.from_numpy(expert_actions(x_base)),
        nn.functional.mse_loss, steps=base_steps, batch=256, lr=1e-3, seed=seed, decay_at=0.7,
    )  # fmt: skip
    paths = {"base": out_dir / "base.safetensors"}
    state = {k: v.detach().contiguous() for k, v in model.state_dict().items()}
    save_file(state, str(paths["base"]), metadata={"activation": "relu"})
    x_mine = make_states(2000, mine_seed)
    paths["mine"] = save_npz(out_dir / "mine.npz", x=x_mine, y=personal_actions(x_mine))
    paths["general"] = save_npz(out_dir / "general.npz", x=make_states(20000, general_seed))
    x_test = make_states(2000, test_seed)
    paths["test"] = save_npz(
        out_dir / "test.npz", x=x_test, y=expert_actions(x_test), y_personal=personal_actions(x_test)
    )
    return paths


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m examples.reach_task", description=__doc__)
    ap.add_argument("out_dir", type=Path)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    paths = write_example(args.out_dir, seed=args.seed)
    from safetensors.torch import load_file

    model = mlp([9, 128, 128, JOINTS])
    model.load_state_dict(load_file(str(paths["base"])))
    test = np.load(paths["test"])
    with torch.no_grad():
        pred = model(torch.from_numpy(test["x"])).numpy()
    for name, path in paths.items():
        print(f"{name:8s} {path}")
    gap = float(np.mean((test["y_personal"] - test["y"]) ** 2))
    print(f"base test mse vs expert: {np.mean((pred - test['y']) ** 2):.5f} (personal gap {gap:.4f})")


if __name__ == "__main__":
    main()
