"""The PRoP objective (paper Eq. 7, made tractable as Eq. 8).

Per step: the personalized loss of each user's key on that user's data, plus the fallback loss
(distillation towards the frozen original) for the null key, K2 = uniform random keys and
K1 = Hamming neighbours of the user keys within ``radius`` (drawn by ``core.key_sampling.KeySampler``,
in key-bit space whatever the key encoding, so the objective is the paper's in both encodings).

A step's rows are laid out as [user rows | sampled-key fallback rows | null rows]; ``prop_loss``
relies on that order (built by ``array.make_batch``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from prop_cli.core.keyed_model import JoinedDeltas
from prop_cli.errors import PropError


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
    # The sampled-key rows are [K1 and K2 | far_rows | code_rows]: --harden's antipode codes and the far
    # codes (hardening), then --harden's code-space negatives. Each a mean term of its
    # own, so that they add to Eq. 8's K1 and K2 term instead of diluting it (docs/hardening.md).
    code_rows: int = 0
    far_rows: int = 0


def row_loss(out: torch.Tensor, target: torch.Tensor, task: str, distill: bool) -> torch.Tensor:
    """Per-row loss: MSE for float targets, cross-entropy for labels, KL to soft targets for distill."""
    if out.dtype == torch.bfloat16:
        out = out.float()  # a bf16 forward (--precision bf16): the loss itself reduces in fp32
    if task == "classification":
        if distill:
            logp = F.log_softmax(target, -1)
            return (logp.exp() * (logp - F.log_softmax(out, -1))).sum(-1)
        return F.cross_entropy(out, target, reduction="none")
    return ((out - target) ** 2).flatten(1).mean(-1)


def prop_loss(
    out: torch.Tensor, batch: Batch, task: str, null_weight: float, key_weight: float = 1.0
) -> tuple[torch.Tensor, dict[str, float]]:
    """Eq. 8: mean personalized loss + key_weight * mean keyed fallback loss (+ the mean loss of the far
    codes, ``Batch.far_rows``, and of --harden's code-space negatives, ``Batch.code_rows``) +
    null_weight * mean null loss."""
    u, n0 = batch.user_rows, batch.null_rows
    ut, ft = batch.user_targets, batch.fallback_targets
    if task == "classification" or ut.dtype != ft.dtype or ut.shape[1:] != ft.shape[1:]:
        personal = row_loss(out[:u], batch.user_targets, task, distill=False).mean()
        fb = row_loss(out[u:], batch.fallback_targets, task, distill=True)
    else:  # one squared error over every row: the same values as per term, fewer small operators
        rows = row_loss(out, torch.cat([ut, ft]), task, distill=False)
        personal, fb = rows[:u].mean(), rows[u:]
    null = fb[-n0:].mean()
    sampled, f, c = fb[:-n0], batch.far_rows, batch.code_rows
    k = len(sampled) - f - c
    keyed = sampled[:k].mean() if k else out.new_zeros(())
    for lo, n in ((k, f), (k + f, c)):
        if n:
            keyed = keyed + sampled[lo : lo + n].mean()
    total = personal + (keyed if key_weight == 1.0 else key_weight * keyed) + null_weight * null
    return total, {"personal": personal.item(), "fallback": keyed.item(), "null": null.item()}


def prop_loss_share(
    out: torch.Tensor, batch: Batch, rows: torch.Tensor, task: str, null_weight: float,
    key_weight: float = 1.0,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Eq. 8 restricted to ``rows`` of the step (``out``: their outputs), as a sum over rows weighted by
    each row's share of its term, so that the shares of all processes add up to ``prop_loss``
    (``distributed``). Returns the loss and its three terms' partial sums (personal, keyed fallback,
    null), to be summed over the processes for the progress line."""
    u, n0, c, f = batch.user_rows, batch.null_rows, batch.code_rows, batch.far_rows
    n = len(batch.key_index)
    n_keyed = n - u - n0 - c - f
    is_user = rows < u
    parts = out.new_zeros(3)
    if is_user.any():
        personal = row_loss(out[is_user], batch.user_targets[rows[is_user]], task, distill=False)
        parts = parts + torch.stack([personal.sum() / u, out.new_zeros(()), out.new_zeros(())])
    fb_rows = rows[~is_user]
    if len(fb_rows):
        fb = row_loss(out[~is_user], batch.fallback_targets[fb_rows - u], task, distill=True)
        null = fb_rows >= n - n0
        code = (fb_rows >= n - n0 - c) & ~null
        far = (fb_rows >= n - n0 - c - f) & ~null & ~code
        sampled = ~null & ~code & ~far
        keyed = fb[sampled].sum() / n_keyed if n_keyed else out.new_zeros(())
        for rows_in, count in ((far, f), (code, c)):
            if count:
                keyed = keyed + fb[rows_in].sum() / count
        parts = parts + torch.stack([out.new_zeros(()), keyed, fb[null].sum() / n0])
    return parts[0] + key_weight * parts[1] + null_weight * parts[2], parts.detach()


def delta_pull(deltas: list[torch.Tensor], keys: slice, of: int | None = None) -> torch.Tensor:
    """Squared distance of the pulled codes' layer scales from 1 (the null key's): rows ``keys`` of each
    layer's delta (K, features), summed over those rows, divided by ``of`` rows (default: their count)
    and by every layer's features. Zero when no key is sampled.

    Both trainers pull K1 and K2 (a random key's code is 64 +- 5.7 bits from the user's) and --harden's
    antipode codes (72-88 bits), never the codes placed nearer the user's: the far codes (40-56 bits)
    and --harden's code-space negatives get the fallback term only. Pulled too, the far codes flattened
    the encoder next to the user's code (tiny SmolVLA: personalization -6.1% against -3.5%; SAC Pendulum,
    code-space negatives: 0.97 -> 0.77). ``of`` counts the far codes all the same: each pulled key keeps
    the weight it had when the far codes were pulled with it. Handed the far codes' share instead, the
    pull on each wrong key tripled on the LeRobot examples (8 sampled keys, 16 far codes) and LeRobot
    Diffusion's user key lost 7.5% of its personalization (2 seeds), against +0.7% keeping the weight."""
    if isinstance(deltas, JoinedDeltas):  # every layer's block side by side already: no cat
        sq = deltas.joined[keys]
    else:
        sq = torch.cat([d[keys] for d in deltas], 1)
    if sq.shape[0] == 0:
        return deltas[0].new_zeros(())
    sq = sq.float().sub(1).pow(2)
    return sq.sum() / ((of or sq.shape[0]) * sq.shape[1])

