"""One connection's policy: the bundle under that connection's key, checked once at connect; ``infer(obs)``
answers openpi's ``{"actions": ...}``.

An array model's session holds its behaviour (``rows``: an unsealed key's deltas, a sealed key's payload,
None for the base), not a folded copy, so the server can run many sessions' rows in one forward of the
base (``rows.run_requests``); behaviours come from and go to the server's ``BehaviourCache``. A LeRobot
policy's session folds its key into its own module and keeps its own queues."""

from __future__ import annotations

import copy
import warnings
from collections.abc import Mapping

import numpy as np
import torch

from prop_cli import constants as C
from prop_cli.bundle import Bundle
from prop_cli.core.keyed_model import key_codes
from prop_cli.errors import PropError
from prop_cli.run import KeyedPolicy
from prop_cli.run.policy import WrongKeyWarning, key_opens_nothing, require_enrolled

from .cache import BehaviourCache
from .chunks import ChunkRequest, ChunkRunner, batchable
from .rows import Behaviour, Deltas, Folded, PayloadTable, Request, gathered, run_requests


def payload_table(bundle: Bundle) -> PayloadTable | None:
    """A sealed bundle's table of payload slots, shared by the server's batches (``rows.PayloadTable``);
    None for an unsealed one."""
    return PayloadTable(bundle.mode.state.spec) if bundle.mode.is_sealed else None


def chunk_runner(
    bundle: Bundle, table: PayloadTable | None, batch_no_key: bool = False
) -> ChunkRunner | None:
    """The runner of a LeRobot bundle whose connections can share forwards (``chunks``); None for an
    array model (``rows``) or a policy with an observation history (Diffusion: a module per connection)."""
    if bundle.loaded.policy is None or not batchable(bundle):
        return None
    return ChunkRunner(bundle, table, batch_no_key)


def any_replica_answers(bundle: Bundle) -> bool:
    """Whether a connection's requests can be answered by any copy of the policy, its state between calls
    being no more than its episode's seed and call count (an array model; a LeRobot policy whose chunk
    needs the frame alone, ``chunks.batchable``): what `prop serve-ray`'s replicas need."""
    return bundle.loaded.policy is None or batchable(bundle)


# An array model's observation entry (openpi's observations are dicts; a LeRobot policy's are its features).
OBSERVATION = "observation"


class Session:
    """The bundle's policy for one connection. ``key`` None: the base (the original, for a bundle as its
    publisher made it). A key enrolled in nothing is a PropError unless ``allow_unenrolled``."""

    def __init__(
        self, bundle: Bundle, key: np.ndarray | None, allow_unenrolled: bool,
        cache: BehaviourCache | None = None, runner: ChunkRunner | None = None,
    ) -> None:  # fmt: skip
        loaded = bundle.loaded
        self.bundle = bundle
        self.input_shape = tuple(bundle.manifest[C.M_IO]["input_shape"])
        self.controller = None
        self.chunk_steps: int | None = None  # a LeRobot policy's actions per infer; None: one step
        self.cached = False  # the behaviour came from the cache (no decryption)
        self.runner = runner  # a LeRobot bundle whose connections share forwards (``chunks``)
        if runner is not None:  # a behaviour for batched rows, and a controller of its own on the base
            self.behaviour = self._behaviour(key, allow_unenrolled, cache)
            self.keyed = self.behaviour is not None
            self.controller = runner.controller()
            self.chunk_steps = self.controller.chunk_steps
            return
        if loaded.policy is None:  # an array model: a behaviour for batched rows
            self.behaviour = self._behaviour(key, allow_unenrolled, cache)
            self.keyed = self.behaviour is not None
            return
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
        self.controller = self.policy.controller
        # openpi clients take a chunk per infer (ActionChunkBroker): the policy's whole chunk (Diffusion:
        # with its observation history on this connection's module); ACT with temporal ensembling, one
        # step at a time from its own queues.
        self.chunk_steps = getattr(self.controller, "chunk_steps", None)

    def _behaviour(self, key, allow: bool, cache: BehaviourCache | None) -> Behaviour:
        """What ``key`` runs, checked as ``KeyedPolicy`` checks it; from ``cache`` when it is there."""
        if key is None:
            return None
        if cache is not None:
            hit, behaviour = cache.get(key)
            if hit:
                self.cached = True
                return behaviour
        bundle, mode, module = self.bundle, self.bundle.mode, self.bundle.loaded.module.eval()
        bits = bundle.check_key(key)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", WrongKeyWarning)  # the server says it once, without the key
            if mode.is_sealed:
                behaviour = mode.payload_for(bits)  # one trial decryption: the check and the payload
                if behaviour is None:
                    key_opens_nothing(mode.not_enrolled(str(bundle.path)), allow)
                elif not gathered(module, behaviour):
                    behaviour = Folded(behaviour.fold(module).eval())
            elif not mode.enrolled(bits):
                key_opens_nothing(mode.not_enrolled(str(bundle.path)), allow)
                behaviour = None
            elif mode.keyed is not None and mode.keyed.module is module:
                with torch.no_grad():
                    codes = key_codes(bits, mode.encoding)
                    behaviour = Deltas([d.detach()[:1] for d in mode.keyed.layer_deltas(codes[:1])])
            else:
                behaviour = Folded(mode.respond(module, bits).eval())
        if cache is not None:
            cache.put(key, behaviour)
        return behaviour

    def observation(self, obs) -> tuple[np.ndarray, bool]:
        """An array model's ``{"observation": x}`` checked: (x as (N, *input_shape) float32, whether it was
        one observation)."""
        if not isinstance(obs, Mapping):
            raise PropError(f"an observation is a dict, not {type(obs).__name__}", "send {name: array}")
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
        single = x.shape == self.input_shape
        return np.ascontiguousarray(x[None] if single else x, np.float32), single

    def request(self, x: np.ndarray) -> Request:
        return Request(self.behaviour, x)

    def answer(self, y: torch.Tensor, single: bool) -> dict:
        """Raw outputs -> openpi's reply, as ``KeyedPolicy.predict`` makes its action (argmax, clip)."""
        loaded = self.bundle.loaded
        out = y.numpy()
        if loaded.continuous is False:
            out = out.argmax(-1)
        elif loaded.action_low is not None and loaded.action_high is not None:
            low, high = np.asarray(loaded.action_low, np.float32), np.asarray(loaded.action_high, np.float32)
            out = np.clip(out, low, high)
        return {"actions": np.asarray(out[0] if single else out)}

    def infer(self, obs) -> dict:
        """openpi's ``infer``: an array model's ``{"observation": x}`` (one observation or a batch) ->
        ``{"actions": KeyedPolicy.predict(x)}``; a LeRobot policy's feature dict -> ``{"actions": its
        chunk}`` (``Controller.action_chunk``; a policy without one: ``select_action(obs)[None]``, a chunk
        of one step from the policy's own queues, kept per connection)."""
        if self.runner is not None:
            return {"actions": self.runner.run([self.chunk_request(obs)])[0].astype(np.float32)}
        if self.controller is not None:
            if not isinstance(obs, Mapping):
                raise PropError(f"an observation is a dict, not {type(obs).__name__}", "send {name: array}")
            if self.chunk_steps is not None:
                return {"actions": np.asarray(self.controller.action_chunk(obs), np.float32)}
            return {"actions": np.asarray(self.policy.select_action(obs), np.float32)[None]}
        x, single = self.observation(obs)
        loaded = self.bundle.loaded
        y = run_requests(loaded.module, self.bundle.mode.keyed, [self.request(x)])[0]
        return self.answer(y, single)

    def chunk_request(self, obs) -> ChunkRequest:
        """A batched LeRobot connection's ``obs`` as a row group of the next forward."""
        return self.runner.request(self.controller, self.behaviour, obs)

    def reset(self, seed: int | None = None) -> None:
        """A new episode for this connection: a LeRobot policy's queues emptied (``seed``: its noise)."""
        if self.runner is not None:
            self.controller.episode, self.controller.calls = int(seed or 0), 0  # its queues are unused
        elif self.controller is not None:
            self.policy.reset(seed)
