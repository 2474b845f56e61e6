"""Running a bundle: the key is turned into behaviour once (folded into a copy of the weights), then
each step is a base step.

``KeyedPolicy(bundle, key).predict(obs)`` is Stable-Baselines3's ``predict(observation, state=None,
episode_start=None, deterministic=True)``: numpy in, ``(action, state)`` out, one observation or a
batch, continuous actions clipped to the bounds the checkpoint records, the argmax for discrete
actions. ``run_policy`` runs a policy with named observation features (LeRobot) over a dataset. The
counterpart for an ONNX export is ``prop_cli.deploy.onnx``.
"""

from __future__ import annotations

import warnings
from dataclasses import replace

import numpy as np
import torch
from torch import nn

from prop_cli import constants as C
from prop_cli.datasources import Dataset
from prop_cli.errors import PropError

from .read import Bundle

ROWS = 256  # frames per forward when running a whole dataset through a policy


class WrongKeyWarning(UserWarning):
    """A key enrolled in nothing of the bundle: the bundle's base runs (which is the original only if the
    bundle is what its publisher made: ``prop verify``)."""


BASE_RUNS = "running the bundle's base, not a keyed behaviour"


def module_for_key(bundle: Bundle, key: np.ndarray | None, *, method: bool = False) -> nn.Module:
    """The bundle's module under ``key``: the base without a key; with one, a copy showing what the key
    unlocks (never written anywhere: it is the personalized policy in the clear). Checked (``modes``):
    a key enrolled in nothing gives the base, with a warning; a bundle changed since the key was
    enrolled is a PropError. ``method``: the method's response to any key, unchecked (an unsealed key
    always goes through the encoder): for audits and the paper's wrong-key measurements only."""
    base = bundle.loaded.module.eval()
    if key is None:
        return base
    bits = bundle.check_key(key)
    if method:
        return bundle.mode.respond(base, bits) or base
    unlocked = bundle.mode.unlock(base, bits)
    if unlocked is None:
        why = bundle.mode.not_enrolled(str(bundle.path))
        warnings.warn(f"{why}: {BASE_RUNS}", WrongKeyWarning, stacklevel=3)
        return base
    return unlocked


class KeyedPolicy:
    """The bundle's module with one key's behaviour folded into a copy of its weights (in memory only):
    what that key's holder enrolled, checked (``module_for_key``; ``method=True``: unchecked)."""

    def __init__(self, bundle: Bundle, key: np.ndarray | None = None, *, method: bool = False) -> None:
        self.module = module_for_key(bundle, key, method=method)
        self.input_shape = tuple(bundle.manifest[C.M_IO]["input_shape"])
        loaded = bundle.loaded
        self.discrete = loaded.continuous is False
        self.low = None if loaded.action_low is None else np.asarray(loaded.action_low, np.float32)
        self.high = None if loaded.action_high is None else np.asarray(loaded.action_high, np.float32)

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """Raw outputs for a batch (N, *input_shape): what ``prop run`` writes."""
        with torch.inference_mode():
            return self.module(torch.from_numpy(np.ascontiguousarray(x, np.float32))).numpy()

    def predict(
        self,
        observation: np.ndarray,
        state: tuple[np.ndarray, ...] | None = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = True,
    ) -> tuple[np.ndarray, tuple[np.ndarray, ...] | None]:
        """SB3's ``predict``: ``(action, state)`` for one observation (``input_shape``) or a batch of them.
        The policies prop keys are feed-forward, so ``state`` comes back as given; the action is the
        deterministic one (the mean, or the argmax): the key changes the policy's output, not its noise."""
        if not deterministic:
            raise PropError(
                "KeyedPolicy.predict(deterministic=False): prop runs the deterministic policy",
                "pass deterministic=True (the mean action, or the argmax)",
            )
        obs = np.asarray(observation, np.float32)
        single = obs.shape == self.input_shape
        y = self(obs[None] if single else obs)
        if self.discrete:
            y = y.argmax(-1)
        elif self.low is not None and self.high is not None:
            y = np.clip(y, self.low, self.high)
        return (y[0] if single else y), state


def run_bundle(bundle: Bundle, x: np.ndarray, key: np.ndarray | None) -> np.ndarray:
    """The bundle's raw outputs on ``x``: with a key, that key's behaviour; without, the base's.

    One call folds the key once; in a control loop keep a ``KeyedPolicy(bundle, key)`` instead.
    """
    return KeyedPolicy(bundle, key)(x)


@torch.no_grad()
def run_policy(bundle: Bundle, data: Dataset, key: np.ndarray | None, flag: str = "--input") -> np.ndarray:
    """A policy bundle's action chunks (N, chunk, action_dim) for every frame of ``data``, in the dataset's
    action units (the policy's postprocessor applied); with a key, that key's behaviour."""
    policy = bundle.loaded.policy
    module = module_for_key(bundle, key)
    if module is not bundle.loaded.module:
        policy = policy.on(module)
    batch = policy.batches(replace(data, y=None), flag)
    n = len(batch["episode_index"])
    feats = {k: batch[k] for k in policy.row_shapes}
    chunks = [policy.chunk({k: v[i : i + ROWS] for k, v in feats.items()}) for i in range(0, n, ROWS)]
    return policy.post(torch.cat(chunks)).float().numpy()
