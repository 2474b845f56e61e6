"""Imitation learning (paper Sec. "Imitation Learning"): dim 2 and 3, key size 128, ~50k parameters.

The expert of ``examples.il_task`` steps towards the goal g; the personalized expert steps towards a
fixed affine transform of g (0.8 x a 90-degree rotation in the first two axes, plus 1), as in the paper.
PRoP personalizes a behaviour-cloned base (128-wide MLP) whose encoder width brings base + encoder to
~50k parameters; the baselines get the same count and are trained from scratch on the same data.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from safetensors.torch import save_file

from examples import il_task
from examples.reproduce import common

TOTAL_PARAMS = 50_000
BASE_HIDDEN = 128


def goal_transform(goal: np.ndarray) -> np.ndarray:
    """g -> 0.8 R g + 1, R a 90-degree rotation of the first two axes (stays inside [-10, 10])."""
    g = np.array(goal, dtype=np.float32, copy=True)
    g[:, 0], g[:, 1] = -goal[:, 1], goal[:, 0]
    return (0.8 * g + 1.0).astype(np.float32)


def personal_actions(x: np.ndarray, dim: int) -> np.ndarray:
    moved = np.concatenate([x[:, :dim], goal_transform(x[:, dim:])], axis=1)
    return il_task.expert_actions(moved, dim)


def make_task(seed: int, dim: int, work: Path, quick: bool) -> common.TaskData:
    n_base, base_steps = (500, 60) if quick else (20000, 6000)  # quick: a smoke run of the pipeline
    base_seed, mine_seed, general_seed, test_seed = (seed * 1000 + 100 * dim + k for k in range(4))
    x_base = il_task.make_states(n_base, base_seed, dim)
    model = il_task.train_base(
        x_base, il_task.expert_actions(x_base, dim), hidden=BASE_HIDDEN, steps=base_steps, seed=seed
    )
    work.mkdir(parents=True, exist_ok=True)
    path = work / "base.safetensors"
    save_file(
        {k: v.contiguous() for k, v in model.state_dict().items()}, str(path), metadata={"activation": "relu"}
    )
    x_user = il_task.make_states(500 if quick else 2000, mine_seed, dim)
    x_test = il_task.make_states(500 if quick else 2000, test_seed, dim)
    return common.TaskData(
        task="regression",
        base=model.eval(),
        base_path=path,
        user_x=x_user,
        user_y=personal_actions(x_user, dim),
        general_x=il_task.make_states(n_base, general_seed, dim),
        test_x=x_test,
        test_y=il_task.expert_actions(x_test, dim),
        test_y_personal=personal_actions(x_test, dim),
    )


def run(out: Path, quick: bool, seeds: int | None, log=print) -> list[dict]:
    budget = common.Budget(baseline_steps=3000)
    if quick:
        budget = common.Budget(prop_steps=40, baseline_steps=40, random_keys=8, hamming_keys=16,
                               t2_restarts=2, t2_steps=10, t2_samples=64)  # fmt: skip
    n_seeds = seeds or (2 if quick else 3)
    results = []
    for dim in (2,) if quick else (2, 3):
        per_seed = []
        params: dict = {}
        for seed in range(n_seeds):
            td = make_task(seed, dim, out / "work" / f"il{dim}-{seed}", quick)
            enc = common.encoder_width(td, TOTAL_PARAMS)
            r = common.run_seed(td, seed, out / "work" / f"il{dim}-{seed}", budget, enc, log=log)
            params = r["_params"]
            per_seed.append(r)
        results.append(
            {
                "name": f"il{dim}",
                "title": f"Imitation learning, dim {dim} (key 128 bits)",
                "objective": "MSE of actions",
                "higher_is_better": False,
                "row_labels": {
                    "general": "general (MSE vs expert)",
                    "personal": "personalized (MSE vs personal expert)",
                    "leakage": "leakage (shared metric)",
                },
                **common.seed_fields(per_seed, params),
                "notes": [
                    "PRoP personalizes a behaviour-cloned base (prop's use case); the paper's Fig. 4 trains "
                    "every method from scratch. Baselines here are trained from scratch on the same data "
                    "(base-labelled fallback states + the user's demonstrations), "
                    f"{budget.baseline_steps} steps.",
                    "Parameters: " + ", ".join(f"{m} {n}" for m, n in params.items()),
                ],
            }
        )
    return results
