"""One step of a policy's training split between two processes' rows, computed in one process: the shares'
losses and gradients add up to the whole step's (prop_cli.train.distributed, row_noise; the policy's
``loss_parts`` / ``joint_parts``)."""

from __future__ import annotations

import torch

from prop_cli.train.distributed import Ranks
from prop_cli.train.policy import drawn, rows, weighted
from prop_cli.train.row_noise import RowNoise


class Shares(Ranks):
    """Rank ``rank`` of two, whose collective sum is the two shares' (set once both are computed)."""

    totals: list

    def sum_tensor(self, t: torch.Tensor) -> torch.Tensor:
        return self.totals[0] + self.totals[1]


def split_matches_whole(policy, user: dict, fallback: dict | None, cut: int) -> None:
    """``user`` rows split at ``cut`` (and ``fallback`` rows, where the policy joins the terms, at half):
    the sum of the two shares' losses and gradients is the whole step's, each row's draws its own."""
    params = [p for p in policy.policy.parameters() if p.requires_grad]
    n_user = len(next(iter(user.values())))
    n_fb = len(next(iter(fallback.values()))) if fallback is not None else 0

    def forward(u: torch.Tensor, f: torch.Tensor):
        if fallback is None:
            return policy.loss_parts(rows(user, u)), None
        return policy.joint_parts(rows(user, u), rows(fallback, f))

    noise, why = RowNoise.probe(
        lambda r, o: forward(torch.arange(r), torch.arange(o)), (0,), policy.policy
    )  # fmt: skip
    assert why is None and noise is not None, why  # the policy draws inside its loss

    def run(u: torch.Tensor, f: torch.Tensor):
        with drawn(noise, 0, u, n_user):
            return forward(u, f)

    def total(parts, pred, ranks: Ranks) -> torch.Tensor:
        out = weighted(parts, ranks)
        return out if pred is None else out + pred.square().sum() / n_fb

    whole = total(*run(torch.arange(n_user), torch.arange(n_fb)), Ranks())
    half = n_fb // 2
    cuts = [(torch.arange(cut), torch.arange(half)), (torch.arange(cut, n_user), torch.arange(half, n_fb))]
    runs = [run(u, f) for u, f in cuts]
    totals = [torch.stack([w.sum() for _, w in parts]).float() for parts, _ in runs]
    split = 0
    for i, (parts, pred) in enumerate(runs):
        ranks = Shares(i, 2)
        object.__setattr__(ranks, "totals", totals)
        split = split + total(parts, pred, ranks)
    assert torch.allclose(split, whole, rtol=1e-5), (split, whole)
    for a, b in zip(torch.autograd.grad(whole, params, allow_unused=True),
                    torch.autograd.grad(split, params, allow_unused=True)):  # fmt: skip
        assert (a is None) == (b is None)
        if a is not None:
            assert torch.allclose(a, b, atol=1e-5 * (1 + float(a.abs().max()))), float((a - b).abs().max())


def memo_terms(policy, frames, fb):
    """The chunk, the joint terms and their gradients on the policy's trained parameters (the prefix
    memo's tests compare them with and without it)."""
    torch.manual_seed(0)
    with torch.no_grad():
        chunk = policy.chunk(frames)
    policy.policy.zero_grad()
    loss, v = policy.joint_terms(frames, fb)
    (loss + v.square().mean()).backward()
    grads = {n: p.grad.clone() for n, p in policy.policy.named_parameters() if p.grad is not None}
    return chunk, loss.detach(), v.detach(), grads


def buffers_as_built(module: torch.nn.Module) -> None:
    """A policy built without random initialisation (``construct``), then loaded: what the checkpoint
    does not hold (non-persistent buffers: rotary frequencies) is what a normal build computes."""
    normal = type(module)(module.config)
    loaded = set(module.state_dict())
    mine, theirs = dict(module.named_buffers()), dict(normal.named_buffers())
    assert mine.keys() == theirs.keys()
    computed = [n for n in theirs if n not in loaded]
    assert computed, "no buffer is computed at build time: nothing to compare"
    assert all(torch.equal(mine[n], theirs[n]) for n in computed)
