"""A small PPO (clipped surrogate, GAE) for the reach experiment, written for this example.

The rollout side is in ``reach``; here: the Gaussian actor-critic, advantages and the PPO losses, kept
separate from the optimiser loop so PRoP can add its fallback terms to the same loss (Eq. 8 with
L' = the PPO objective).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import nn


def mlp(inp: int, hidden: int, out: int) -> nn.Sequential:
    return nn.Sequential(
        nn.Linear(inp, hidden), nn.Tanh(), nn.Linear(hidden, hidden), nn.Tanh(), nn.Linear(hidden, out)
    )


@dataclass
class PPOConfig:
    lr: float = 3e-4
    rollout: int = 2000  # env steps per update (40 episodes of 50 steps)
    epochs: int = 8
    minibatch: int = 250
    gamma: float = 0.95
    lam: float = 0.95
    clip: float = 0.2
    value_coef: float = 0.5
    init_log_std: float = -0.7


def gaussian_logp(mean: torch.Tensor, log_std: torch.Tensor, act: torch.Tensor) -> torch.Tensor:
    var = (2 * log_std).exp()
    return (-((act - mean) ** 2) / (2 * var) - log_std - 0.5 * np.log(2 * np.pi)).sum(-1)


def gae(rew: np.ndarray, val: np.ndarray, last_val: np.ndarray, gamma: float, lam: float) -> np.ndarray:
    """Advantages for (T, E) arrays of fixed-horizon episodes (no early ends; the horizon is truncation)."""
    adv = np.zeros_like(rew)
    nxt_adv = np.zeros(rew.shape[1:], dtype=rew.dtype)
    nxt_val = last_val
    for t in range(len(rew) - 1, -1, -1):
        delta = rew[t] + gamma * nxt_val - val[t]
        nxt_adv = delta + gamma * lam * nxt_adv
        adv[t] = nxt_adv
        nxt_val = val[t]
    return adv


def ppo_terms(
    mean: torch.Tensor,
    log_std: torch.Tensor,
    act: torch.Tensor,
    old_logp: torch.Tensor,
    adv: torch.Tensor,
    value: torch.Tensor,
    ret: torch.Tensor,
    cfg: PPOConfig,
) -> torch.Tensor:
    """Clipped-surrogate policy loss + value loss (to minimise)."""
    ratio = (gaussian_logp(mean, log_std, act) - old_logp).exp()
    surr = torch.min(ratio * adv, ratio.clamp(1 - cfg.clip, 1 + cfg.clip) * adv)
    return -surr.mean() + cfg.value_coef * ((value - ret) ** 2).mean()
