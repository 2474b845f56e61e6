"""A bundle as a policy for a control loop: the key is folded once, then each step is a base step.

``KeyedPolicy(bundle, key).predict(obs)`` works like Stable-Baselines3's ``predict(obs,
deterministic=True)``: numpy in and out, one observation or a batch, continuous actions clipped to the
bounds the checkpoint records, the argmax for discrete actions. The counterpart for an ONNX export is
``prop_cli.onnx_runtime.OnnxPolicy``.
"""

from __future__ import annotations

import warnings

import numpy as np
import torch

from . import constants as C
from .bundle import Bundle
from .keyed import key_codes


class WrongKeyWarning(UserWarning):
    """A key that opens no user record of a sealed bundle: the base (the original) runs."""


def sealed_module(bundle: Bundle, key: np.ndarray | None) -> torch.nn.Module:
    """A sealed bundle's module for ``key``: the user's payload folded into a copy of the base if the
    key opens a record; the base itself (the original) if not, with a warning when a key was given."""
    base = bundle.loaded.module.eval()
    if key is None:
        return base
    opened = bundle.sealed.open(key)
    if opened is None:
        warnings.warn(
            f"the key opens no user of {bundle.path}: running the base (the original's behaviour)",
            WrongKeyWarning,
            stacklevel=3,
        )
        return base
    return opened.payload.fold(base)


class KeyedPolicy:
    """The bundle's module with one key's delta folded into a copy of its weights (in memory only)."""

    def __init__(self, bundle: Bundle, key: np.ndarray | None = None) -> None:
        if key is not None:
            bundle.check_key(key)
        # Never write the folded copy anywhere: it is the personalized policy in the clear.
        if bundle.sealed is not None:
            self.module = sealed_module(bundle, key)
        elif key is not None:
            self.module = bundle.keyed.eval().fold(key_codes(key, bundle.key_encoding))
        else:
            self.module = bundle.keyed.eval().module
        self.input_shape = tuple(bundle.manifest[C.M_IO]["input_shape"])
        loaded = bundle.loaded
        self.discrete = loaded.continuous is False
        self.low = None if loaded.action_low is None else np.asarray(loaded.action_low, np.float32)
        self.high = None if loaded.action_high is None else np.asarray(loaded.action_high, np.float32)

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """Raw outputs for a batch (N, *input_shape): what ``prop run`` writes."""
        with torch.inference_mode():
            return self.module(torch.from_numpy(np.ascontiguousarray(x, np.float32))).numpy()

    def predict(self, obs: np.ndarray) -> np.ndarray:
        """Actions for one observation (``input_shape``) or a batch of them, as SB3's predict gives."""
        obs = np.asarray(obs, np.float32)
        single = obs.shape == self.input_shape
        y = self(obs[None] if single else obs)
        if self.discrete:
            y = y.argmax(-1)
        elif self.low is not None and self.high is not None:
            y = np.clip(y, self.low, self.high)
        return y[0] if single else y
