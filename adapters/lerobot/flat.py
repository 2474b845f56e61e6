"""A LeRobot policy seen as an array model (``LeRobotProtocol.flat``, ``flat_rows``): one input tensor in,
one output tensor out.

Policies take named observation features and predict an action chunk. The audit, its probes and the
metrics work on one input tensor and one output tensor, so this view flattens both:

- input: the policy's features, each in the policy's normalised units (its preprocessor applied),
  flattened and concatenated in the order of the policy's config (``input_features``; with the
  policy's observation history where it has one, Diffusion's n_obs_steps frames);
- output: the deployed action chunk (ACT: eval mode, VAE latent 0; Diffusion: the horizon sampled
  from the policy's noise seed), flattened, in normalised units.

The recorded chunks a user's data holds are flattened the same way by ``prop_cli.fit``.
Metrics on this view are the ones `prop personalize` reports for policies (docs/metrics.md:
personalization, leakage, fidelity on whole chunks in normalised units), so audit and personalize
figures compare.
"""

from __future__ import annotations

import math

import torch

from prop_adapters.base import FlatView, PolicyProtocol


class FlatModule(FlatView):
    """``x`` (B, F) -> the deployed chunk (B, chunk * action_dim), both in normalised units.

    The policy module's children are registered here under their own names, so named_modules(), the
    state dict and the keyed layers' names are exactly the policy's (LeRobot's); the same layer
    objects run, so a KeyedModel's hooks on them fire.
    """

    def __init__(self, policy: PolicyProtocol) -> None:
        super().__init__()
        for name, child in policy.policy.named_children():
            self.add_module(name, child)
        self.protocol = policy  # not a module attribute of ours: its children are registered above
        self.layout = [(k, tuple(s)) for k, s in policy.row_shapes.items()]
        self.width = sum(math.prod(s) for _, s in self.layout)

    def features(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        out, at = {}, 0
        for name, shape in self.layout:
            n = math.prod(shape)
            out[name] = x[:, at : at + n].reshape(x.shape[0], *shape)
            at += n
        return out

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.protocol.chunk(self.features(x)).flatten(1)
