"""A bundle as a policy for a control loop: the key is folded once, then each step is a base step.

``KeyedPolicy(bundle, key).predict(obs)`` works like Stable-Baselines3's ``predict(obs,
deterministic=True)``: numpy in and out, one observation or a batch, continuous actions clipped to the
bounds the checkpoint records, the argmax for discrete actions. The counterpart for an ONNX export is
``prop_cli.onnx_runtime.OnnxPolicy``.
"""

from __future__ import annotations

import numpy as np
import torch

from . import constants as C
from .bundle import Bundle
from .keyed import key_codes


class KeyedPolicy:
    """The bundle's module with one key's delta folded into a copy of its weights (in memory only)."""

    def __init__(self, bundle: Bundle, key: np.ndarray | None = None) -> None:
        if key is not None:
            bundle.check_key(key)
        km = bundle.keyed.eval()
        # Never write the folded copy anywhere: it is the personalized policy in the clear.
        self.module = km.fold(key_codes(key, bundle.key_encoding)) if key is not None else km.module
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
