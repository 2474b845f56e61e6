"""One connection's policy: the bundle under that connection's key, folded once at connect, with its own
queues; ``infer(obs)`` answers openpi's ``{"actions": ...}``."""

from __future__ import annotations

import copy
import warnings
from collections.abc import Mapping

import numpy as np

from prop_cli import constants as C
from prop_cli.bundle import Bundle
from prop_cli.errors import PropError
from prop_cli.run import KeyedPolicy
from prop_cli.run.policy import WrongKeyWarning, require_enrolled

# An array model's observation entry (openpi's observations are dicts; a LeRobot policy's are its features).
OBSERVATION = "observation"


class Session:
    """The bundle's policy for one connection. ``key`` None: the base (the original, for a bundle as its
    publisher made it). A key enrolled in nothing is a PropError unless ``allow_unenrolled``."""

    def __init__(self, bundle: Bundle, key: np.ndarray | None, allow_unenrolled: bool) -> None:
        self.keyed = key is not None and require_enrolled(bundle, key, allow_unenrolled)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", WrongKeyWarning)  # the server says it once, without the key
            self.policy = KeyedPolicy(bundle, key, allow_unenrolled=allow_unenrolled)
        loaded = bundle.loaded
        if self.policy.controller is not None and self.policy.module is loaded.module:
            # No key: the base module holds LeRobot's queues; each connection gets a copy of its own.
            module = copy.deepcopy(loaded.module).eval()
            self.policy.module = module
            self.policy.controller = loaded.policy.on(module).controller(module)
        self.input_shape = tuple(bundle.manifest[C.M_IO]["input_shape"])

    def infer(self, obs) -> dict:
        """openpi's ``infer``: an array model's ``{"observation": x}`` (one observation or a batch) ->
        ``{"actions": KeyedPolicy.predict(x)}``; a LeRobot policy's feature dict -> ``{"actions":
        select_action(obs)[None]}`` (a chunk of one step: the policy's own queues, kept per connection)."""
        if not isinstance(obs, Mapping):
            raise PropError(f"an observation is a dict, not {type(obs).__name__}", "send {name: array}")
        if self.policy.controller is not None:
            return {"actions": np.asarray(self.policy.select_action(obs), np.float32)[None]}
        x = obs.get(OBSERVATION)
        if not isinstance(x, np.ndarray) or x.dtype.kind not in "biuf":
            raise PropError(
                f"an array model's observation is {{{OBSERVATION!r}: numeric array}} "
                f"(got keys {sorted(map(str, obs))[:8]})",
                f"send {{{OBSERVATION!r}: array of shape {self.input_shape} or (N, ...)}}",
            )
        if x.shape != self.input_shape and x.shape[1:] != self.input_shape:
            raise PropError(
                f"observation shape {x.shape}; the model takes {self.input_shape} or (N, ...) of them",
                "send arrays of the model's input shape",
            )
        action, _ = self.policy.predict(x)
        return {"actions": np.asarray(action)}

    def reset(self) -> None:
        self.policy.reset()
