"""A policy bundle (LeRobot ACT) seen as an array model, for `prop run` and `prop attack`.

Policies take named observation features and predict an action chunk. The audit, its probes and the
metrics work on one input tensor and one output tensor, so this view flattens both:

- input: the policy's features, each in the policy's normalised units (its preprocessor applied),
  flattened and concatenated in the order of the policy's config (``input_features``);
- output: the deployed action chunk (ACT: eval mode, VAE latent 0), flattened, in normalised units;
- targets: each frame's recorded action chunk, cut with the policy's own delta indices and padded
  at episode ends as LeRobot pads (the last action repeats), flattened the same way.

Metrics on this view are the ones `prop personalize` reports for policies (docs/metrics.md:
personalization, leakage, fidelity on whole chunks in normalised units), so audit and personalize
figures compare. `prop run` instead returns chunks in the dataset's action units (postprocessor).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import torch
from torch import nn

from prop_adapters import LoadedModel

from .bundle import Bundle
from .datasources import Dataset
from .keyed import key_codes

ROWS = 256  # frames per forward when running a whole dataset


class FlatPolicy(nn.Module):
    """``x`` (B, F) -> the deployed chunk (B, chunk * action_dim), both in normalised units.

    The policy module's children are registered here under their own names, so named_modules(), the
    state dict and the keyed layers' names are exactly the policy's (LeRobot's); the same layer
    objects run, so a KeyedModel's hooks on them fire.
    """

    def __init__(self, policy) -> None:
        super().__init__()
        for name, child in policy.policy.named_children():
            self.add_module(name, child)
        self.protocol = policy  # not a module attribute of ours: its children are registered above
        self.layout = [(k, tuple(s)) for k, s in policy.input_features.items()]
        self.width = sum(math.prod(s) for _, s in self.layout)

    def __setattr__(self, name: str, value) -> None:
        if name == "protocol":  # keep the policy object out of _modules (its children are ours)
            object.__setattr__(self, name, value)
        else:
            super().__setattr__(name, value)

    def features(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        out, at = {}, 0
        for name, shape in self.layout:
            n = math.prod(shape)
            out[name] = x[:, at : at + n].reshape(x.shape[0], *shape)
            at += n
        return out

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.protocol.chunk(self.features(x)).flatten(1)


def flatten_features(policy, batch: dict[str, torch.Tensor]) -> torch.Tensor:
    """The policy's features of a batch, flattened and concatenated in the policy's order."""
    return torch.cat([batch[k].flatten(1) for k in policy.input_features], dim=1)


def flat_chunks(policy, batch: dict[str, torch.Tensor], path: str) -> Dataset:
    """A policy's batch -> x (N, F) normalised features and y (N, chunk * action_dim) recorded chunks
    (None without actions)."""
    x = flatten_features(policy, batch).numpy().astype(np.float32)
    y = batch["action"].flatten(1).numpy().astype(np.float32) if "action" in batch else None
    return Dataset(x=x, y=y, path=path, meta={"episode_index": batch["episode_index"].numpy()})


def flat_dataset(policy, data: Dataset, flag: str) -> Dataset:
    """A LeRobot Dataset as the array model takes it; rows ordered by episode and frame, as the policy
    cuts its chunks."""
    return flat_chunks(policy, policy.batches(data, flag), data.path)


def flat_module(loaded: LoadedModel) -> FlatPolicy:
    return FlatPolicy(loaded.policy).eval()


def array_bundle(bundle: Bundle) -> Bundle:
    """The bundle as an array model: the same layers, encoder and manifest, a flat input and output.

    The returned bundle's KeyedModel hooks the same layer objects; the original bundle's hooks are
    removed so that each layer is scaled once.
    """
    loaded = bundle.loaded
    if loaded.policy is None:
        return bundle
    flat = flat_module(loaded)
    view_loaded = replace(loaded, module=flat, input_shape=(flat.width,), policy=None)
    if bundle.is_sealed:  # no encoder: records fold into the flat module by the layers' names
        return replace(bundle, loaded=view_loaded)
    km = bundle.keyed
    km.remove_hooks()
    return replace(bundle, loaded=view_loaded, keyed=km.on(flat).eval())


def policy_module(bundle: Bundle, key: np.ndarray | None) -> nn.Module:
    """The policy module that acts under ``key``: unsealed, the key's delta folded into a copy; sealed,
    the opened record's payload folded in, or the base (the original) when the key opens none."""
    if key is not None:
        bundle.check_key(key)
    if bundle.is_sealed:
        from .policy import sealed_module

        return sealed_module(bundle, key)
    if key is None:
        return bundle.loaded.module
    return bundle.keyed.fold(key_codes(key, bundle.key_encoding))


@torch.no_grad()
def run_policy(bundle: Bundle, data: Dataset, key: np.ndarray | None, flag: str = "--input") -> np.ndarray:
    """The bundle's action chunks (N, chunk, action_dim) for every frame of ``data``, in the dataset's
    action units (the policy's postprocessor applied); with a key, that key's behaviour."""
    policy = bundle.loaded.policy
    module = policy_module(bundle, key)
    if module is not bundle.loaded.module:
        policy = type(policy)(module, policy.pre, policy.post)
    batch = policy.batches(replace(data, y=None), flag)
    n = len(batch["episode_index"])
    feats = {k: batch[k] for k in policy.input_features}
    chunks = [policy.chunk({k: v[i : i + ROWS] for k, v in feats.items()}) for i in range(0, n, ROWS)]
    return policy.post(torch.cat(chunks)).float().numpy()
