"""LeRobot ACT through the policy protocol: what differs from the base (``policy.LeRobotProtocol``).

- **Deployed chunk**: the transformer's action chunk in eval mode (dropout off, the VAE latent 0), as
  ``select_action`` runs it; deterministic, so the fallback term distils the original's chunk (L1,
  ACT's own loss's distance), cached once per frame.
- **User term**: the policy's own loss (masked L1 on the chunk plus its KL).
- **Keyed layers** by default (measured in examples/RESULTS.md, "LeRobot ACT"): the feed-forward
  layers of the transformer encoder and decoder and the action head. Not the attention out_proj (never
  called through its forward) nor the VAE encoder (training only).
- **Memo** (``memo``): the image backbone's feature maps, per camera frame, computed once while the
  audit or a report runs every key over the same frames (the backbone is never keyed by default, and
  it is most of a small ACT's compute: a ResNet-18 per frame).
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from itertools import chain

import torch
from torch.nn.utils import parametrize

from .flow_matching import Bounded, row_digest
from .policy import ACTION, PAD, LeRobotProtocol

ACT_LAYERS = [r"model\.(encoder|decoder)\.layers\.\d+\.linear[12]", r"model\.action_head"]
BACKBONE_BYTES = 256 << 20  # feature maps kept by ``memo`` (a 96x96 frame's is 18 KB; 480x480, 0.5 MB)


def _fixed(module: torch.nn.Module) -> bool:
    """Whether ``module`` computes the same for the same input now: nothing trains through it (no
    gradient will flow into its parameters) and no hook or parametrization (a key, a payload) is on it."""
    training = torch.is_grad_enabled() and any(p.requires_grad for p in module.parameters())
    return not training and not any(
        m._forward_pre_hooks or m._forward_hooks or parametrize.is_parametrized(m) for m in module.modules()
    )


def distinct_rows(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(rows, which)``: the first row of each distinct row of ``x``, in order, and for every row of
    ``x`` the position in ``rows`` of the row it equals, bit for bit. A projection proposes which rows
    are equal; every proposal is checked on the bytes, and a row that fails the check stands alone."""
    n = len(x)
    if n < 2:
        return torch.arange(n), torch.zeros(n, dtype=torch.long)
    flat = x.detach().reshape(n, -1)
    raw = flat.contiguous().view(torch.uint8)
    # Fixed weights, no random draw (a policy's training replays its draws: ``prop_cli.train.row_noise``).
    golden = (5**0.5 - 1) / 2
    w = torch.arange(1, flat.shape[1] + 1, dtype=torch.float64, device=flat.device).mul_(golden).frac_()
    proj = flat.to(torch.float64).nan_to_num(0.0, 1e300, -1e300) @ w
    _, group = torch.unique(proj, return_inverse=True)
    first = torch.full((int(group.max()) + 1,), n, dtype=torch.long, device=group.device)
    first.scatter_reduce_(0, group, torch.arange(n, device=group.device), "amin")
    lead = first[group]  # each row's proposed twin: the first row of its group
    same = (raw == raw[lead]).all(1)
    lead = torch.where(same, lead, torch.arange(n, device=lead.device)).cpu()
    rows = torch.unique(lead)  # sorted: the first row of each distinct row
    return rows, torch.searchsorted(rows, lead)


@contextlib.contextmanager
def backbone_memo(backbone: torch.nn.Module, limit: int = BACKBONE_BYTES) -> Iterator[None]:
    """Within: a backbone of ``backbone``'s class (ACT's IntermediateLayerGetter) returns each frame's
    feature map from a memo where that frame went through it before with the same weights, else runs as
    it is. The class is patched, not the instance, because the audit runs copies that share the
    weights (a sealed bundle's searches and their controls). A row is keyed by its content and the
    identity, storage and version of every weight and buffer (an optimizer step, in place, bumps a
    version), so a changed backbone never serves an old map; while gradients would flow into a
    backbone, or a hook or parametrization sits on it, it runs as LeRobot's."""
    kept = Bounded(limit)
    cls = type(backbone)
    had = cls.__dict__.get("forward")  # the class's own forward, or None where it inherits one
    forward = cls.forward

    def memo_forward(self: torch.nn.Module, x: torch.Tensor) -> dict[str, torch.Tensor]:
        if x.requires_grad or not _fixed(self):
            return forward(self, x)
        weights = chain(self.parameters(), self.buffers())
        head = tuple((id(t), t.data_ptr(), t._version) for t in weights)
        # The audit runs keys as batch copies of a few frames: each distinct frame is digested once.
        rows, which = distinct_rows(x)
        keys = [(head, row_digest(x[i])) for i in rows.tolist()]
        todo = list(dict.fromkeys(k for k in keys if k not in kept))
        if todo:
            first = {k: i for i, k in reversed(list(zip(rows.tolist(), keys)))}
            maps = forward(self, x[[first[k] for k in todo]])["feature_map"]
            for j, k in enumerate(todo):
                kept.keep(k, maps[j].clone())
        return {"feature_map": torch.stack(kept.rows(keys))[which]}

    cls.forward = memo_forward
    try:
        yield
    finally:
        if had is None:
            del cls.forward
        else:
            cls.forward = had


class ACTProtocol(LeRobotProtocol):
    """ACT through the policy protocol (see the module docstring)."""

    default_layers = ACT_LAYERS
    label = "ACT"

    def describe(self) -> dict:
        return {"chunk_size": self.config.chunk_size}

    def memo(self) -> contextlib.AbstractContextManager:
        backbone = getattr(self.model, "backbone", None)  # none without camera features
        return contextlib.nullcontext() if backbone is None else backbone_memo(backbone)

    def _model_batch(self, batch: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        # What ACTPolicy.forward does before calling its model: the list of camera tensors.
        b = {k: v for k, v in batch.items() if k != "episode_index"}
        if self.config.image_features:
            b["observation.images"] = [b[k] for k in self.config.image_features]
        return b

    def loss_parts(self, batch: dict[str, torch.Tensor]) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """ACTPolicy.forward's loss as its two parts: the L1 over the valid (not padded) chunk steps,
        each row weighted by its valid steps, and the VAE's KL, a mean over rows (kl_weight applied)."""
        self.policy.train()
        c = self.config
        actions_hat, (mu, log_sigma_x2) = self.policy.model(self._model_batch(batch))
        abs_err = torch.nn.functional.l1_loss(batch[ACTION], actions_hat, reduction="none")
        valid = ~batch[PAD].unsqueeze(-1)
        l1 = (abs_err * valid).sum() / (valid.sum() * abs_err.shape[-1]).clamp_min(1)
        parts = [(l1, valid.sum((1, 2)).float())]
        if c.use_vae and log_sigma_x2 is not None:
            kld = (-0.5 * (1 + log_sigma_x2 - mu.pow(2) - log_sigma_x2.exp())).sum(-1).mean()
            parts.append((kld * c.kl_weight, torch.ones(len(mu), device=mu.device)))
        return parts

    def chunk(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        # The deployed path: eval mode (dropout off, and the VAE latent is 0, as select_action runs it).
        self.policy.eval()
        return self.policy.model(self._model_batch({k: batch[k] for k in self.row_shapes}))[0]


__all__ = ["ACT_LAYERS", "ACTProtocol"]
