"""LeRobot ACT through the policy protocol: what differs from the base (``policy.LeRobotProtocol``).

- **Deployed chunk**: the transformer's action chunk in eval mode (dropout off, the VAE latent 0), as
  ``select_action`` runs it; deterministic, so the fallback term distils the original's chunk (L1,
  ACT's own loss's distance), cached once per frame.
- **User term**: the policy's own loss (masked L1 on the chunk plus its KL).
- **Keyed layers** by default (measured in examples/RESULTS.md, "LeRobot ACT"): the feed-forward
  layers of the transformer encoder and decoder and the action head. Not the attention out_proj (never
  called through its forward) nor the VAE encoder (training only).
"""

from __future__ import annotations

import torch

from .policy import ACTION, PAD, LeRobotProtocol

ACT_LAYERS = [r"model\.(encoder|decoder)\.layers\.\d+\.linear[12]", r"model\.action_head"]


class ACTProtocol(LeRobotProtocol):
    """ACT through the policy protocol (see the module docstring)."""

    default_layers = ACT_LAYERS
    label = "ACT"

    def describe(self) -> dict:
        return {"chunk_size": self.config.chunk_size}

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
