"""The shared metrics: personalization, leakage, fidelity (definitions: docs/metrics.md).

``b`` = the original model's output, ``p`` = the user's target, ``o`` = the bundle's output under a key.
Regression outputs are (..., B, d) floats; classification uses logits (..., B, C) and labels p (B,).
Functions taking ``o`` of shape (K, B, ...) return one value per key.
"""

from __future__ import annotations

import math

import torch

# Below this the user's targets equal the original's outputs: there is nothing that could leak.
_EPS = 1e-12


def personalization(o: torch.Tensor, p: torch.Tensor, b: torch.Tensor, task: str) -> float:
    """Regression: 1 - mse(o, p) / mse(b, p). Classification: accuracy of o on p."""
    if task == "classification":
        return (o.argmax(-1) == p).float().mean().item()
    return 1.0 - ((o - p) ** 2).mean().item() / max(((b - p) ** 2).mean().item(), _EPS)


def leakage(o: torch.Tensor, p: torch.Tensor, b: torch.Tensor, task: str) -> torch.Tensor:
    """Per key: how far its outputs move from the original towards the user's behaviour, in [0, 1].

    Regression: the projection of the key's whole move ``o - b`` (all samples, all outputs) onto the
    whole gap ``p - b``, as a fraction of the gap, clipped to [0, 1]:
    ``clip(mean_i <o_i - b_i, p_i - b_i> / mean_i |p_i - b_i|^2, 0, 1)``. The clip comes after the
    mean, so outputs that scatter around ``b`` average to 0 instead of counting their positive half.
    Classification: the share of samples with ``p != argmax b`` where ``argmax o == p``.
    """
    if task == "classification":
        differs = p != b.argmax(-1)
        if not differs.any():
            return torch.zeros(o.shape[0])
        return ((o.argmax(-1) == p) & differs).float().sum(-1) / differs.sum()
    return lean(o, p, b, task).clamp(0, 1)


def bounded_leakage(o: torch.Tensor, p: torch.Tensor, b: torch.Tensor, task: str) -> torch.Tensor:
    """Per key: leakage at no more than the user's own fidelity cost, in [0, 1].

    A move larger than the gap from the original to the user's behaviour is scaled back to the gap's
    size before it is scored, so a search cannot reach 1 by moving far in a direction that merely
    shares a component with the gap. Regression: ``clip(<m, g> / (|g| max(|m|, |g|)), 0, 1)`` with
    ``m = o - b``, ``g = p - b`` over all samples and outputs (= leakage while ``|m| <= |g|``, the
    cosine of m and g beyond). Classification: hits / max(changed predictions, samples where
    ``p != argmax b``), i.e. leakage, charged for every prediction changed beyond the ones needed.
    """
    if task == "classification":
        differs = p != b.argmax(-1)
        if not differs.any():
            return torch.zeros(o.shape[0])
        hits = ((o.argmax(-1) == p) & differs).float().sum(-1)
        changed = (o.argmax(-1) != b.argmax(-1)).float().sum(-1)
        return hits / changed.clamp(min=float(differs.sum()))
    gap = (p - b).flatten(1) if p.dim() > 1 else (p - b)[:, None]
    move = (o - b).flatten(2) if o.dim() > 2 else (o - b)[..., None]
    g2 = (gap**2).sum()
    if g2 <= _EPS * gap.shape[0]:
        return torch.zeros(o.shape[0])
    m = (move**2).sum((-2, -1)).sqrt()
    g = g2.sqrt()
    return ((move * gap).sum((-2, -1)) / (g * torch.maximum(m, g))).clamp(0, 1)


def fidelity(o: torch.Tensor, b: torch.Tensor, task: str) -> torch.Tensor:
    """Per key: agreement with the original (classification) or mse(o, b) (regression)."""
    if task == "classification":
        return (o.argmax(-1) == b.argmax(-1)).float().mean(-1)
    return ((o - b) ** 2).flatten(1).mean(-1)


def target_error(o: torch.Tensor, y: torch.Tensor, task: str) -> torch.Tensor:
    """Per key: mse against targets y (regression) or accuracy on labels y (classification)."""
    if task == "classification":
        return (o.argmax(-1) == y).float().mean(-1)
    return ((o - y) ** 2).flatten(1).mean(-1)


def summarize(values: torch.Tensor, worst: str) -> dict:
    """Mean with a 95% interval (normal approximation) and the worst key (``worst`` = max|min)."""
    v = values.double().flatten()
    n = v.numel()
    mean = v.mean().item()
    half = 1.96 * v.std().item() / math.sqrt(n) if n > 1 else 0.0
    w = v.max().item() if worst == "max" else v.min().item()
    return {"n": n, "mean": mean, "ci95": [mean - half, mean + half], "worst": w}


def lean(o: torch.Tensor, p: torch.Tensor, b: torch.Tensor, task: str) -> torch.Tensor:
    """Per key: the signed direction of its move from the original, towards (> 0) or away from (< 0) the
    user's behaviour; 0 when there is no gap to move along.

    Regression: leakage's projection before the clip,
    ``mean_i <o_i - b_i, p_i - b_i> / mean_i |p_i - b_i|^2``.
    Classification: on the samples with ``p != argmax b``, the mean change of the probability of ``p``,
    ``softmax(o)[p] - softmax(b)[p]``."""
    if task == "classification":
        differs = p != b.argmax(-1)
        if not differs.any():
            return torch.zeros(o.shape[0])
        idx = p[differs].long()[:, None]  # (M, 1)
        po = o[:, differs].softmax(-1).gather(-1, idx.expand(o.shape[0], -1, -1))  # (K, M, 1)
        pb = b[differs].softmax(-1).gather(-1, idx)  # (M, 1)
        return (po - pb).squeeze(-1).mean(-1)
    gap = (p - b).flatten(1) if p.dim() > 1 else (p - b)[:, None]
    move = (o - b).flatten(2) if o.dim() > 2 else (o - b)[..., None]
    norm = (gap**2).sum()
    if norm <= _EPS * gap.shape[0]:
        return torch.zeros(o.shape[0])
    return (move * gap).sum((-2, -1)) / norm


def sign_test(below: int, above: int) -> float:
    """Two-sided exact sign test: the chance, with each of ``below + above`` untied keys equally likely on
    either side, of a split at least as uneven as this one (ties are left out before). 1.0 with none."""
    n = below + above
    if n == 0:
        return 1.0
    k = min(below, above)
    tail = sum(math.comb(n, i) for i in range(k + 1)) / 2**n
    return min(1.0, 2 * tail)


# A group's wrong keys drift systematically when a two-sided sign test over its keys rejects "either side
# equally likely" at this level (docs/metrics.md, "Systematic drift").
SYSTEMATIC_P = 0.05


def sides(values: list[float]) -> dict:
    """Keys on each side of 0 (``values``: per key, signed, > 0 = the side the caller names ``above``),
    with the sign test's p and ``systematic``: p < SYSTEMATIC_P."""
    above = sum(v > 0 for v in values)
    below = sum(v < 0 for v in values)
    p = sign_test(below, above)
    return {"keys": len(values), "below": below, "above": above, "ties": len(values) - below - above,
            "p": p, "systematic": p < SYSTEMATIC_P}  # fmt: skip
