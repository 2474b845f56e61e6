"""What every LeRobot policy shares under the policy protocol (``PolicyProtocol``): batches cut from a
dataset's frames with the policy's own delta indices, its processors, how it is built from its folder,
and the closed-loop controller (``Controller``: LeRobot's preprocessor -> ``select_action`` with its
queues -> postprocessor).

``LeRobotProtocol`` is the base; each policy type is one file beside it holding its class (deriving from
this one only) and one line in ``registry.POLICIES``. What a sampling policy adds (its chunk's sampler,
its fallback term) is a part it holds, a ``Denoiser`` (``flow_matching.FlowMatching`` for the VLAs). No
lerobot import at module level: the policy, preprocessor and postprocessor objects come from
``adapter``.
"""

from __future__ import annotations

import contextlib
import io
import os
import sys
from abc import ABC, abstractmethod
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

import numpy as np
import torch

from prop_adapters.base import FRAME, PolicyProtocol
from prop_cli.constants import ENV_DEBUG, TASK
from prop_cli.errors import PropError

ACTION, PAD = "action", "action_is_pad"
TOKENS, MASK = "observation.language.tokens", "observation.language.attention_mask"  # a VLA's instruction
FALLBACK_DRAWS = 8  # a denoising policy's (t, noise) draws per fallback frame (``Denoiser``)
POOL_BATCH = 256  # rows per forward while the fallback targets are drawn


def older_than(version: str, than: str) -> bool:
    """``version`` (a manifest's ``lerobot_version``, e.g. "0.4.4") is an older release than ``than``."""

    def parts(v: str) -> tuple[int, ...]:
        out = []
        for p in v.split("."):
            digits = "".join(c for c in p if c.isdigit()) if p[:1].isdigit() else ""
            if not digits:
                break
            out.append(int(digits))
        return tuple(out)

    return parts(version) < parts(than)


@dataclass
class Built:
    """A LeRobot policy built from its folder: the policy, the preprocessor overrides its folder needs,
    and the files the bundle carries besides the folder's config and processors (path under the
    bundle's LeRobot folder -> bytes)."""

    policy: torch.nn.Module
    overrides: dict = field(default_factory=dict)
    files: dict[str, bytes] = field(default_factory=dict)


def construct(
    policy_class, config, weights: Mapping[str, torch.Tensor | tuple[int, ...]], where: str
) -> torch.nn.Module:
    """``policy_class(config)`` for ``weights`` (tensors, or their shapes), built first on the meta
    device (shapes only: a config.json claiming a huge model allocates nothing) and refused in one line
    unless its state dict has exactly the weights' names and shapes (what ``load_state_dict(strict=True)``
    then needs). A policy that cannot be built on the meta device is built for real and checked by
    loading. Built without random initialisation (every caller then loads every weight, strictly):
    a real-size SmolVLA's 32-layer VLM is otherwise drawn at random only to be overwritten."""
    try:
        with torch.device("meta"):
            probe = policy_class(config)
    except Exception:  # noqa: BLE001 - LeRobot's or transformers' own, on the meta device only
        probe = None
    if probe is not None:
        want = {k: tuple(v.shape) for k, v in probe.state_dict().items()}
        got = {k: tuple(v.shape) if isinstance(v, torch.Tensor) else tuple(v) for k, v in weights.items()}
        if want != got:
            name = sorted(set(want) ^ set(got) or {k for k in want if want[k] != got[k]})[0]
            shown = {d: str(x[name]) if name in x else "absent" for d, x in (("w", got), ("c", want))}
            raise PropError(
                f"{where}: the weights do not fit the policy config.json describes (tensor {name[:120]!r}: "
                f"{shown['w']} in the weights, {shown['c']} in the config); nothing was built",
                "check that config.json and model.safetensors belong together, or restore the bundle",
            )
    with no_init():
        return policy_class(config)


# What LeRobot's from_pretrained prints on stdout at every local load (prop's own results go there).
LEROBOT_CHATTER = ("Loading weights from local directory",)


@contextlib.contextmanager
def lerobot_quiet() -> Iterator[None]:
    """Within: LeRobot's own prints (``LEROBOT_CHATTER``) dropped, any other print moved to stderr;
    ``PROP_DEBUG`` set, every line kept (on stderr)."""
    buffer = io.StringIO()
    try:
        with contextlib.redirect_stdout(buffer):
            yield
    finally:
        keep = bool(os.environ.get(ENV_DEBUG))
        for line in buffer.getvalue().splitlines():
            if keep or line.strip() not in LEROBOT_CHATTER:
                print(line, file=sys.stderr)


def no_init() -> contextlib.AbstractContextManager:
    """transformers' ``no_init_weights`` (torch's and transformers' initialisers made no-ops), where
    this transformers has it."""
    try:
        from transformers.initialization import no_init_weights
    except ImportError:  # transformers 4 or none: initialised as before
        return contextlib.nullcontext()
    return no_init_weights()


# The registered processor steps every LeRobot policy's own pipelines use that neither import code nor
# load models, tokenizers or files by a name their config gives (read in lerobot 0.6's processor
# sources). Each policy adds its own (``LeRobotProtocol.vetted_steps``): an allow-list, since each LeRobot
# release registers new steps that load by name (0.6: eo1_qwen_processor, molmoact2_pack_inputs, ...).
COMMON_STEPS = frozenset({
    "rename_observations_processor", "to_batch_processor", "device_processor", "normalizer_processor",
    "unnormalizer_processor",
})  # fmt: skip


class Denoiser(ABC):
    """How a denoising policy samples its deployed chunk and what its fallback term distils (Diffusion's
    U-Net, a VLA's flow-matching expert), held by its protocol (``LeRobotProtocol.make_denoiser``).

    In eval mode the denoiser is deterministic given (observation, x_t, t). Each fallback frame gets
    ``FALLBACK_DRAWS`` rows, each with what ``draws`` draws for it (a time and a noise) and the ``x_t``
    that ``noised`` makes of the original's deployed chunk for the frame; the keyed policy's prediction
    on each row (``output``) is distilled towards the frozen original's on the same inputs, MSE (a
    denoising loss's own distance)."""

    @abstractmethod
    def chunk(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        """The deployed chunk (``PolicyProtocol.chunk``), its noise drawn from the policy's noise seed."""

    @abstractmethod
    def draws(self, rows: int, generator: torch.Generator) -> dict[str, torch.Tensor]:
        """The random draws of ``rows`` fallback rows (``{"t", "eps"}``), in the order always drawn."""

    @abstractmethod
    def noised(self, x0: torch.Tensor, draws: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """``{"x_t", "t"}`` of each row: its frame's clean chunk ``x0`` noised with its ``draws``."""

    @abstractmethod
    def output(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        """The denoiser's prediction on fallback rows (observation, x_t, t), in eval mode."""

    # True where the denoiser follows its own sampler (``states``: ``--fallback-times trajectory``).
    follows_sampler: bool = False

    def states(self, batch: dict[str, torch.Tensor], draws: dict[str, torch.Tensor]) -> torch.Tensor:
        """Each row's state in the sampler at its drawn step (``draws``' ``k``), the sampler run on the
        row's observation from the row's own noise: ``--fallback-times trajectory``'s x_t."""
        raise NotImplementedError

    # True where the user term and the fallback output can share one forward (``joint_terms``).
    joins_terms: bool = False

    def joint_terms(
        self, user: dict[str, torch.Tensor], fallback: dict[str, torch.Tensor]
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``(the policy's loss on user, output(fallback))`` from one forward (``PolicyProtocol``)."""
        raise NotImplementedError

    def row_weights(self, batch: dict[str, torch.Tensor]) -> torch.Tensor | None:
        """Each row's weight in the normaliser of the policy's loss; None: a mean over rows."""
        return None

    def distance(self, pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        return ((pred - target) ** 2).flatten(1).mean(1)

    def memo(self) -> contextlib.AbstractContextManager:
        """``PolicyProtocol.memo``: nothing kept unless the model has something to keep."""
        return contextlib.nullcontext()

    def describe(self) -> dict:
        """What `prop inspect` shows of the sampler and its model."""
        return {}


class LeRobotProtocol(PolicyProtocol):
    """A LeRobot policy through the policy protocol: what every policy type shares. A type is one class
    deriving from this one (its file beside this one, one line in ``registry.POLICIES``): it sets
    ``default_layers`` and ``vetted_steps``, and either implements ``chunk`` (a deterministic chunk,
    distilled as it is: ACT) or returns its ``Denoiser`` from ``make_denoiser`` (Diffusion; the VLAs,
    through ``flow_matching.FlowMatching``). A VLA also sets ``takes_instruction``: its rows then hold
    the frame alone and its instruction as tokens, and it overrides ``build`` to find the files its
    processors read by name (a tokenizer)."""

    fallbacks = ("distill",)
    # The registered processor steps this policy's folders may hold (``adapter.processor_code``).
    vetted_steps: ClassVar[frozenset[str]] = COMMON_STEPS
    # Registered processor steps that load by a name their config gives, accepted in this policy's
    # folders because ``build`` points them at the folder's own files (SmolVLA's tokenizer).
    own_steps: ClassVar[frozenset[str]] = frozenset()
    # Set where the policy acts on a language instruction (the preprocessor's ``task``): a VLA.
    takes_instruction: ClassVar[bool] = False
    label: ClassVar[str] = "this policy"  # how messages name the policy type

    def __init__(self, policy, pre, post, noise_seed: int = 0) -> None:
        self.policy, self.pre, self.post = policy, pre, post
        self.config = policy.config
        self.noise_seed = noise_seed
        self.denoiser = self.make_denoiser()

    def make_denoiser(self) -> Denoiser | None:
        """The policy's denoiser; None: its deployed chunk is deterministic (``chunk``)."""
        return None

    @property
    def model(self) -> torch.nn.Module:
        """The policy's model (``policy.model``: what its own forward calls)."""
        return self.policy.model

    @classmethod
    def build(
        cls, policy_class, folder: Path, weights: dict[str, torch.Tensor] | None, where: str, *,
        contained: bool = False, made_with: str | None = None, as_held: bool = False,
    ) -> Built:  # fmt: skip
        """LeRobot's ``policy_class`` from ``folder``: its own weights (``from_pretrained``), or
        ``weights`` (a bundle's base) into the policy its config describes. ``contained``: the folder
        is a bundle's, and the policy reads nothing outside it. ``made_with``: the lerobot version a
        bundle was made under, where a policy runs differently under today's (``smolvla``).
        ``as_held``: the folder's weights taken in the file's dtypes (``load_into``) where the policy
        loads them tensor by tensor (SmolVLA, pi0, pi0.5; the small ones are cast after, ``finish``)."""
        if weights is None:
            with lerobot_quiet():
                return Built(policy_class.from_pretrained(str(folder)))
        from lerobot.configs.policies import PreTrainedConfig

        config = PreTrainedConfig.from_pretrained(str(folder))
        if getattr(config, "pretrained_backbone_weights", None):
            # ACT's image backbone would load torchvision's weights (a download, or the torch cache)
            # only for ``weights`` to replace every one of them.
            config.pretrained_backbone_weights = None
        policy = construct(policy_class, config, weights, where)
        policy.load_state_dict(weights, strict=True)
        return Built(policy)

    def on(self, module) -> LeRobotProtocol:
        other = type(self)(module, self.pre, self.post, self.noise_seed)
        other.instruction = self.instruction
        return other

    def flat(self) -> torch.nn.Module:
        from .flat import FlatModule

        return FlatModule(self).eval()

    def flat_rows(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        return torch.cat([batch[k].flatten(1).float() for k in self.row_shapes], dim=1)

    @property
    def input_features(self) -> dict[str, tuple[int, ...]]:
        return {k: tuple(f.shape) for k, f in self.config.input_features.items()}

    @property
    def history(self) -> list[int] | None:
        """The observation frames a row holds, relative to its own (Diffusion: the last n_obs_steps);
        None: the frame alone, without a time axis (ACT, and a VLA, which reads the last frame only)."""
        deltas = getattr(self.config, "observation_delta_indices", None)
        return None if deltas is None or self.takes_instruction else list(deltas)

    @property
    def row_shapes(self) -> dict[str, tuple[int, ...]]:
        h = self.history
        shapes = {k: s if h is None else (len(h), *s) for k, s in self.input_features.items()}
        if self.takes_instruction:  # the instruction's tokens and mask, padded to the tokenizer's width
            width = self.config.tokenizer_max_length
            shapes |= {TOKENS: (width,), MASK: (width,)}
        return shapes

    def _windows(self, episodes: np.ndarray, deltas: list[int]) -> tuple[np.ndarray, np.ndarray]:
        """Row indices t + d for every row t and delta d, clamped to t's episode; and where they fell out."""
        n = len(episodes)
        starts = np.r_[0, np.flatnonzero(np.diff(episodes)) + 1]
        ends = np.r_[starts[1:], n] - 1
        ep_of = np.repeat(np.arange(len(starts)), np.diff(np.r_[starts, n]))
        idx = np.arange(n)[:, None] + np.asarray(deltas)[None, :]
        lo, hi = starts[ep_of][:, None], ends[ep_of][:, None]
        return np.clip(idx, lo, hi), (idx < lo) | (idx > hi)

    def batches(self, data, flag: str) -> dict[str, torch.Tensor]:
        x = data.x if isinstance(data.x, dict) else {}
        for name, shape in self.input_features.items():
            if name not in x:
                raise PropError(
                    f"{flag} {data.path}: no feature '{name}', which the policy takes "
                    f"(the data has {', '.join(sorted(x)) or 'no features'})",
                    "record the policy's input features (`prop inspect` lists them)",
                )
            if tuple(x[name].shape[1:]) != shape:
                raise PropError(
                    f"{flag} {data.path}: feature '{name}' has shape {tuple(x[name].shape[1:])}, the policy "
                    f"takes {shape}",
                    "use data recorded for this policy",
                )
        order = np.lexsort((x["frame_index"], x["episode_index"]))
        episodes = x["episode_index"][order]
        if self.history is None:
            out = {k: torch.from_numpy(x[k][order]).float() for k in self.input_features}
        else:  # each row's observation history, the episode's first frame repeated before it (as LeRobot)
            obs_idx, _ = self._windows(episodes, self.history)
            out = {k: torch.from_numpy(x[k][order][obs_idx]).float() for k in self.input_features}
        if data.y is not None:
            want = tuple(self.config.output_features[ACTION].shape)
            if tuple(data.y.shape[1:]) != want:
                raise PropError(
                    f"{flag} {data.path}: actions have shape {tuple(data.y.shape[1:])}, the policy's {want}",
                    "use data recorded for this policy",
                )
            # The policy's own action window (LeRobot's action_delta_indices), padded at episode ends.
            idx, pad = self._windows(episodes, list(self.config.action_delta_indices))
            out[ACTION] = torch.from_numpy(data.y[order][idx]).float()
            out[PAD] = torch.from_numpy(pad)
        out = self.pre(out | self._instructions(x, order, flag, data.path))
        out = {k: v for k, v in out.items() if isinstance(v, torch.Tensor)}
        if self.takes_instruction:  # the tokenizer pads to the batch's longest and cuts at its width
            pad = self.config.tokenizer_max_length - out[TOKENS].shape[1]
            out[TOKENS] = torch.nn.functional.pad(out[TOKENS], (0, pad))
            out[MASK] = torch.nn.functional.pad(out[MASK].bool(), (0, pad))
        out["episode_index"] = torch.from_numpy(episodes.astype(np.int64))
        return out

    def _instructions(self, x: dict, order: np.ndarray, flag: str, path: str) -> dict:
        """What the preprocessor takes beside the tensors: a VLA's task text per frame."""
        if not self.takes_instruction:
            return {}
        if TASK not in x:
            raise PropError(
                f"{flag} {path}: no task text per frame, which {self.label} takes as its instruction",
                "record the dataset with a task for every frame (LeRobotDataset.add_frame(..., task=...))",
            )
        return {"task": [str(t) for t in x[TASK][order]]}

    # ---- the deployed chunk and the fallback term: the policy's own, or its denoiser's ----------------

    def chunk(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        if self.denoiser is None:
            raise NotImplementedError(f"{type(self).__name__} has no denoiser: it implements chunk")
        return self.denoiser.chunk(batch)

    def fallback_pool(
        self, batch: dict[str, torch.Tensor], chunks: torch.Tensor, original: PolicyProtocol,
        generator: torch.Generator,
    ) -> tuple[dict[str, torch.Tensor], torch.Tensor]:  # fmt: skip
        if self.denoiser is None:
            return super().fallback_pool(batch, chunks, original, generator)
        return self._denoiser_pool(batch, chunks, original, generator)

    def _denoiser_pool(
        self, batch: dict[str, torch.Tensor], chunks: torch.Tensor, original: PolicyProtocol,
        generator: torch.Generator, rows_per_forward: int = POOL_BATCH,
    ) -> tuple[dict[str, torch.Tensor], torch.Tensor]:  # fmt: skip
        """A denoising policy's fallback rows: FALLBACK_DRAWS per frame, each with the ``{"x_t", "t"}``
        the denoiser makes of the frame's chunk (``fallback_noise`` then ``fallback_inputs``), and the
        original's output on each, ``rows_per_forward`` rows at a time."""
        rows = {k: v.repeat_interleave(FALLBACK_DRAWS, 0) for k, v in batch.items()}
        noise = self.fallback_noise(len(chunks), generator)
        noise.pop(FRAME)
        rows |= self.fallback_inputs(chunks.repeat_interleave(FALLBACK_DRAWS, 0), noise)
        n = len(rows["t"])
        with torch.no_grad():
            targets = torch.cat([
                original.fallback_output({k: v[i : i + rows_per_forward] for k, v in rows.items()})
                for i in range(0, n, rows_per_forward)
            ])  # fmt: skip
        return rows, targets

    def fallback_noise(self, frames: int, generator: torch.Generator) -> dict[str, torch.Tensor] | None:
        if self.denoiser is None:
            return None  # the pool's rows are the frames, their targets the original's chunks
        draws = self.denoiser.draws(frames * FALLBACK_DRAWS, generator)
        return {FRAME: torch.arange(frames).repeat_interleave(FALLBACK_DRAWS), **draws}

    def fallback_inputs(self, x0: torch.Tensor, noise: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        return self.denoiser.noised(x0, noise)

    @property
    def follows_sampler(self) -> bool:
        """Whether ``fallback_states`` holds: the policy's sampler states can be fallback inputs."""
        return self.denoiser is not None and self.denoiser.follows_sampler

    def fallback_states(self, batch: dict[str, torch.Tensor], noise: dict[str, torch.Tensor]) -> torch.Tensor:
        """``--fallback-times trajectory``: each row's state in this policy's own sampler at its drawn step
        (``Denoiser.states``), which ``fallback_inputs`` then takes in place of the clean chunk."""
        return self.denoiser.states(batch, noise)

    def fallback_output(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        return self.chunk(batch) if self.denoiser is None else self.denoiser.output(batch)

    def fallback_distance(self, pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        if self.denoiser is None:
            return super().fallback_distance(pred, target)
        return self.denoiser.distance(pred, target)

    @property
    def joins_terms(self) -> bool:
        return self.denoiser is not None and self.denoiser.joins_terms

    def joint_terms(
        self, user: dict[str, torch.Tensor], fallback: dict[str, torch.Tensor]
    ) -> tuple[torch.Tensor, torch.Tensor]:
        return self.denoiser.joint_terms(user, fallback)

    def row_weights(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        weights = None if self.denoiser is None else self.denoiser.row_weights(batch)
        return super().row_weights(batch) if weights is None else weights

    def memo(self) -> contextlib.AbstractContextManager:
        return contextlib.nullcontext() if self.denoiser is None else self.denoiser.memo()

    def describe(self) -> dict:
        return {} if self.denoiser is None else self.denoiser.describe()

    def loss(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        self.policy.train()
        return self.policy.forward({k: v for k, v in batch.items() if k != "episode_index"})[0]

    def example(self, rows: int, data: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        idx = torch.arange(rows) % len(data[next(iter(self.row_shapes))])
        return {k: data[k][idx] for k in self.row_shapes}

    def controller(self, module: torch.nn.Module) -> Controller:
        return Controller(
            module, self.pre, self.post, self.input_features, self.noise_seed,
            instruction=self.instruction if self.takes_instruction else None,
        )  # fmt: skip


def call_seed(noise_seed: int, episode: int, call: int) -> int:
    """The seed of torch's global generator for one ``select_action`` call of an episode."""
    return int(np.random.SeedSequence([noise_seed, episode, call]).generate_state(1)[0])


class Controller:
    """Closed loop: LeRobot's preprocessor -> ``select_action`` (its queues: ``n_action_steps`` actions
    per chunk, Diffusion's ``n_obs_steps`` observation history) -> postprocessor.

    An observation is LeRobot's dict: feature name -> array or tensor, one frame (the feature's shape)
    or a batch of them, in the units the policy's preprocessor takes (a uint8 camera frame is made CHW
    in [0, 1], HWC accepted, as LeRobot's ``preprocess_observation`` does). A policy that takes an
    instruction (``instruction`` not None) reads the dict's ``task`` entry, else ``instruction``.

    LeRobot's samplers (Diffusion's DDPM/DDIM steps, SmolVLA's noise) draw from torch's global
    generator. Each call runs with that generator seeded with ``call_seed(noise seed, the episode's
    seed, the call's number)`` and restored afterwards: an episode's noise is reproducible and the same
    under every key, and nothing else's random stream moves."""

    def __init__(
        self, module, pre, post, features: dict[str, tuple[int, ...]], noise_seed: int = 0,
        instruction: str | None = None,
    ) -> None:  # fmt: skip
        self.module, self.pre, self.post = module.eval(), pre, post
        self.features = {k: tuple(s) for k, s in features.items()}
        self.noise_seed, self.instruction = noise_seed, instruction
        self.reset()  # a new controller starts an episode, whatever the module's queues held

    def reset(self, seed: int | None = None) -> None:
        """A new episode: LeRobot's queues emptied; ``seed`` (the episode's) seeds its noise."""
        self.module.reset()
        self.episode, self.calls = int(seed or 0), 0

    @torch.no_grad()
    def select_action(self, obs: Mapping) -> np.ndarray:
        """The action for ``obs`` in the dataset's action units: (action_dim,) for one frame, (N,
        action_dim) for a batch."""
        x, single = self.inputs(obs)
        seed = call_seed(self.noise_seed, self.episode, self.calls)
        self.calls += 1
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            action = self.post(self.module.select_action(self.pre(x))).numpy()
        return action[0] if single else action

    # Policies whose whole chunk ``action_chunk`` answers: those whose predict_action_chunk needs nothing
    # but the frame (ACT, SmolVLA, pi0, pi0.5; stateless: ``stateless_chunk``), and those that keep an
    # observation history on their module (Diffusion: ``HISTORY``), whose chunk is LeRobot's own
    # select_action from an empty action queue, the queue then handed out whole.
    CHUNKED: tuple[str, ...] = ("act", "smolvla", "pi0", "pi05", "diffusion")
    HISTORY: tuple[str, ...] = ("diffusion",)

    @property
    def chunk_steps(self) -> int | None:
        """Actions per ``action_chunk`` (the policy's ``n_action_steps``); None where it has none here
        (ACT with temporal ensembling; pi0 with relative actions, whose postprocessor reads the state)."""
        config = getattr(self.module, "config", None)
        if getattr(config, "type", None) not in self.CHUNKED or getattr(
            config, "temporal_ensemble_coeff", None
        ) or getattr(config, "use_relative_actions", False):  # fmt: skip
            return None
        return int(config.n_action_steps)

    @property
    def stateless_chunk(self) -> bool:
        """Whether the chunk depends on this frame alone (and the noise): many connections' frames can
        then share one forward of one module (``prop serve``'s batching)."""
        return self.chunk_steps is not None and self.module.config.type not in self.HISTORY

    def call_noise_seed(self) -> int:
        """The seed of this call's noise (``call_seed``), counting the call."""
        seed = call_seed(self.noise_seed, self.episode, self.calls)
        self.calls += 1
        return seed

    @torch.no_grad()
    def action_chunk(self, obs: Mapping) -> np.ndarray:
        """The next ``chunk_steps`` actions for ``obs``, in the dataset's action units: what as many
        ``select_action`` calls from an empty queue give, in one call ((steps, action_dim) for one frame,
        (N, steps, action_dim) for a batch). A stateless chunk leaves the queues as they are; a policy
        with an observation history adds ``obs`` to it, as select_action does."""
        steps = self.chunk_steps
        if steps is None:
            raise PropError("this policy answers one action at a time (select_action)", "call select_action")
        x, single = self.inputs(obs)
        seed = self.call_noise_seed()
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            batch = self.pre(x)
            if self.module.config.type in self.HISTORY:
                chunk = self._history_chunk(batch, steps)
            else:
                chunk = self.module.predict_action_chunk(batch)[:, :steps]
        return self.post_chunk(chunk, single)

    def post_chunk(self, chunk: torch.Tensor, single: bool) -> np.ndarray:
        """A raw (N, steps, dim) chunk through the postprocessor: dataset units, one frame's unbatched."""
        b, t = chunk.shape[:2]
        action = self.post(chunk.reshape(b * t, -1)).reshape(b, t, -1).numpy()
        return action[0] if single else action

    def _history_chunk(self, batch: dict, steps: int) -> torch.Tensor:
        """LeRobot's select_action from an empty action queue (it adds the frame to the observation
        history and fills the queue with the chunk), then the whole queue: (N, steps, dim)."""
        queue = self.module._queues[ACTION]
        queue.clear()
        first = self.module.select_action(batch)
        rest = list(queue)
        queue.clear()
        return torch.stack([first, *rest], dim=1)[:, :steps]

    def inputs(self, obs: Mapping) -> tuple[dict, bool]:
        """``obs`` as the preprocessor takes it, with a batch axis; and whether it came without one."""
        names = ", ".join(self.features)
        if not isinstance(obs, Mapping):
            raise PropError(
                f"a LeRobot policy takes a dict of observation features ({names}), not {type(obs).__name__}",
                "pass {feature name: array}, as LeRobot's select_action takes it",
            )
        x, rows = {}, set()
        for k, shape in self.features.items():
            if k not in obs:
                raise PropError(
                    f"the observation has no {k!r}, which the policy takes (it has {sorted(map(str, obs))})",
                    f"pass every input feature: {names}",
                )
            v = obs[k] if isinstance(obs[k], torch.Tensor) else torch.from_numpy(np.ascontiguousarray(obs[k]))
            if v.dtype == torch.uint8:  # a camera frame as rendered: 0..255, HWC -> CHW
                if len(shape) == 3 and tuple(v.shape[-3:]) == (shape[1], shape[2], shape[0]) != shape:
                    v = v.movedim(-1, -3)
                v = v.float() / 255.0
            v = v.float()
            if tuple(v.shape) == shape:
                v, n = v[None], None
            elif tuple(v.shape[1:]) == shape:
                n = len(v)
            else:
                raise PropError(
                    f"observation {k!r} has shape {tuple(v.shape)}; the policy takes {shape} (one frame) "
                    f"or (N, {', '.join(map(str, shape))}) (a batch)",
                    "pass the feature as the policy's config.json input_features give it",
                )
            x[k] = v
            rows.add(n)
        if len(rows) > 1:
            raise PropError(f"the observation's features have different batch sizes ({sorted(rows)})",
                            "give every feature one frame, or the same N frames")  # fmt: skip
        n = rows.pop()  # None: one frame, without a batch axis
        if self.instruction is not None:
            task = obs.get(TASK) or self.instruction
            if not task:
                raise PropError(
                    "this policy acts on a language instruction, and none was given",
                    "pass --instruction 'the task text your data was recorded with' (in Python: "
                    "KeyedPolicy(..., instruction=...) or a 'task' entry in the observation)",
                )
            x[TASK] = [task] * (n or 1) if isinstance(task, str) else list(task)
        return x, n is None
