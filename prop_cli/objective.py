"""The PRoP objective (paper Eq. 7, made tractable as Eq. 8).

Per step: the personalized loss of each user's key on that user's data, plus the fallback loss
(distillation towards the frozen original) for the null key, K2 = uniform random keys and
K1 = Hamming neighbours of the user keys within ``radius``. Neighbours are drawn in key-bit space,
whatever the key encoding, so the objective is the paper's in both encodings.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from .errors import PropError


def check_user_keys(keys: list[np.ndarray], radius: int) -> None:
    """Users whose keys are within 2 * radius would have overlapping K1 sets: refuse them."""
    for i in range(len(keys)):
        for j in range(i + 1, len(keys)):
            d = int((keys[i] != keys[j]).sum())
            if d < 2 * radius:
                raise PropError(
                    f"the keys of users {i + 1} and {j + 1} are {d} bits apart, closer than twice "
                    f"--hamming-radius ({2 * radius})",
                    "give each user an independent key (prop keygen) or lower --hamming-radius",
                )


class KeySampler:
    """Draws K1 neighbours and K2 random keys (as 0/1 bits) from a seeded generator."""

    def __init__(self, user_keys: list[np.ndarray], radius: int, rng: np.random.Generator) -> None:
        self.users = np.stack(user_keys).astype(np.uint8)
        self.bits = self.users.shape[1]
        self.radius = min(radius, self.bits)
        self.rng = rng
        # Distance 1 has only `bits` members per user: walk through all of them in turn so every
        # 1-bit neighbour is seen every few steps, instead of hoping random draws cover them.
        self._order = rng.permutation(self.bits)
        self._next = 0

    def neighbours(self, n: int) -> np.ndarray:
        if n == 0:
            return np.zeros((0, self.bits), np.uint8)
        owner = self.rng.integers(0, len(self.users), n)
        keys = self.users[owner].copy()
        n1 = n // 4
        flips = self._order[(self._next + np.arange(n1)) % self.bits]
        self._next += n1
        keys[np.arange(n1), flips] ^= 1
        dist = self.rng.integers(1, self.radius + 1, n - n1)
        ranks = self.rng.random((n - n1, self.bits)).argsort(1)
        keys[n1:] ^= (ranks < dist[:, None]).astype(np.uint8)
        return keys

    def random(self, n: int) -> np.ndarray:
        keys = self.rng.integers(0, 2, (n, self.bits), dtype=np.uint8)
        # A uniform key equal to a user key has probability 2^-bits; exclude it anyway (K - K').
        for u in self.users:
            same = (keys == u).all(1)
            keys[same, 0] ^= 1
        return keys


@dataclass
class Batch:
    """One step: distinct samples x, and rows (sample, key) with their targets."""

    x: torch.Tensor
    sample_index: torch.Tensor
    key_index: torch.Tensor  # into [user codes..., sampled codes..., null]
    codes: torch.Tensor  # (K, n) ±1 codes of user keys then sampled keys; null is the row after
    user_rows: int
    null_rows: int
    user_targets: torch.Tensor  # targets of the first user_rows rows
    fallback_targets: torch.Tensor  # original's outputs for the remaining rows


def row_loss(out: torch.Tensor, target: torch.Tensor, task: str, distill: bool) -> torch.Tensor:
    """Per-row loss: MSE for float targets, cross-entropy for labels, KL to soft targets for distill."""
    if task == "classification":
        if distill:
            logp = F.log_softmax(target, -1)
            return (logp.exp() * (logp - F.log_softmax(out, -1))).sum(-1)
        return F.cross_entropy(out, target, reduction="none")
    return ((out - target) ** 2).flatten(1).mean(-1)


def prop_loss(
    out: torch.Tensor, batch: Batch, task: str, null_weight: float
) -> tuple[torch.Tensor, dict[str, float]]:
    """Eq. 8: mean personalized loss + mean keyed fallback loss + null_weight * mean null loss."""
    u, n0 = batch.user_rows, batch.null_rows
    personal = row_loss(out[:u], batch.user_targets, task, distill=False).mean()
    fb = row_loss(out[u:], batch.fallback_targets, task, distill=True)
    null = fb[-n0:].mean()
    keyed = fb[:-n0].mean() if fb.shape[0] > n0 else out.new_zeros(())
    total = personal + keyed + null_weight * null
    return total, {"personal": personal.item(), "fallback": keyed.item(), "null": null.item()}
